"""Engines and sessions for the queue database.

SQLite (the default, one file under the data directory) and PostgreSQL (`postgresql+psycopg://`)
run the same code. On SQLite a transaction that may write starts with BEGIN IMMEDIATE: it takes
the write lock up front, so two writers queue instead of one failing with "database is locked"
when its read transaction tries to become a write (`sqlite_writer`). Writers do not overlap, so
keep them short: every queue operation commits before it returns. Read-only work
(`labelqueue.transaction.reading`) asks for the `READ_ONLY` execution option instead.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import Connection, make_url
from sqlalchemy.orm import Session, sessionmaker

from labelqueue.sqlite_writer import (
    BUSY_TIMEOUT_S,
    READ_ONLY,
    Checkpointer,
    SQLiteConnection,
    begin_sqlite,
)


def make_engine(
    url: str, *, foreign_keys: bool = True, background_checkpoints: bool = False
) -> Engine:
    """An engine for `url`; on SQLite with WAL, a busy timeout, foreign keys, BEGIN IMMEDIATE for
    transactions that may write and a deferred, lock-free BEGIN for `READ_ONLY` ones.

    `foreign_keys=False` is for migrations only: SQLite's batch mode recreates tables that
    others reference, which enforcement would refuse.

    `background_checkpoints` (SQLite): the engine's commits never copy the WAL back into the
    database file; a thread of its own does, twice a second (`Checkpointer`). Otherwise SQLite
    does it in whichever commit finds the WAL over 1 000 pages, and the server's event loop
    would wait out the copying and syncing (benchmarks/README.md).
    """
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(parsed, pool_pre_ping=True)

    database = parsed.database or ""
    a_file = database not in ("", ":memory:") and not database.startswith("file:")
    if a_file:
        Path(database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(parsed, connect_args={"factory": SQLiteConnection})
    # Threads of one process queue for the write lock on a Python lock, which wakes the next
    # one as soon as it is free; SQLite's busy handler would instead poll with sleeps of up to
    # 100 ms, which made the label API's slowest requests. SQLite's own lock still decides (for
    # other processes too), so a thread that waits too long here just goes on to it.
    writer = threading.Lock()

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # pysqlite would otherwise emit its own deferred BEGIN; the "begin" hook below does it.
        dbapi_connection.isolation_level = None
        dbapi_connection.writer = writer
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
        cursor.execute(f"PRAGMA foreign_keys={'ON' if foreign_keys else 'OFF'}")
        # Durable at every checkpoint of the WAL, and much faster than FULL; safe in WAL mode.
        cursor.execute("PRAGMA synchronous=NORMAL")
        if background_checkpoints:
            cursor.execute("PRAGMA wal_autocheckpoint=0")
        cursor.close()

    if background_checkpoints and a_file:
        checkpointer = Checkpointer(database)
        event.listen(engine, "engine_disposed", lambda _engine: checkpointer.stop())

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        dbapi_connection = connection.connection.dbapi_connection
        assert isinstance(dbapi_connection, SQLiteConnection)
        read_only = bool(connection.get_execution_options().get(READ_ONLY))
        begin_sqlite(dbapi_connection, read_only=read_only)

    return engine


def session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions whose objects stay readable after commit without touching the database again."""
    return sessionmaker(engine, expire_on_commit=False)

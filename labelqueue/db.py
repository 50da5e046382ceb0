"""Engines, sessions and schema migration for the queue database.

SQLite (the default, one file under the data directory) and PostgreSQL (`postgresql+psycopg://`)
run the same code. On SQLite every transaction starts with BEGIN IMMEDIATE: it takes the write
lock up front, waiting up to the busy timeout, so two writers queue instead of one failing with
"database is locked" when its read transaction tries to become a write. The price is that
transactions do not overlap, so keep them short: every queue operation commits before it
returns, and a session used for other reads should be committed or closed promptly.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import Connection, make_url
from sqlalchemy.exc import ArgumentError, NoSuchModuleError
from sqlalchemy.orm import Session, sessionmaker


def sqlite_url(data_dir: str | Path) -> str:
    """The embedded default: the SQLite file `queue.db` in the data folder."""
    return f"sqlite:///{Path(data_dir) / 'queue.db'}"


DEFAULT_URL = sqlite_url("data")
VALID_URLS = "sqlite:///PATH or postgresql+psycopg://USER:PASSWORD@HOST/DATABASE"


def check_url(url: str) -> str:
    """`url` if SQLAlchemy can open databases of its kind; ValueError saying what is valid."""
    try:
        parsed = make_url(url)
        parsed.get_dialect()
    except (ArgumentError, NoSuchModuleError, ValueError):
        shown = url.split("@")[-1] if "@" in url else url  # never echo a password
        raise ValueError(
            f"{shown!r} is not a database URL this app can open; use {VALID_URLS}"
        ) from None
    if parsed.get_backend_name() not in ("sqlite", "postgresql"):
        raise ValueError(
            f"{parsed.get_backend_name()} databases are not supported; use {VALID_URLS}"
        )
    return url
BUSY_TIMEOUT_S = 30.0
MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"


def make_engine(url: str, *, foreign_keys: bool = True) -> Engine:
    """An engine for `url`; on SQLite with WAL, a busy timeout, foreign keys and BEGIN IMMEDIATE.

    `foreign_keys=False` is for migrations only: SQLite's batch mode recreates tables that
    others reference, which enforcement would refuse.
    """
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(parsed, pool_pre_ping=True)

    database = parsed.database
    if database and database != ":memory:" and not database.startswith("file:"):
        Path(database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(parsed)

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection: Any, _record: Any) -> None:
        # pysqlite would otherwise emit its own deferred BEGIN; the "begin" hook below does it.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
        cursor.execute(f"PRAGMA foreign_keys={'ON' if foreign_keys else 'OFF'}")
        # Durable at every checkpoint of the WAL, and much faster than FULL; safe in WAL mode.
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.close()

    # Threads of one process queue for the write lock on a Python lock, which wakes the next
    # one as soon as it is free; SQLite's busy handler would instead poll with sleeps of up to
    # 100 ms, which made the label API's slowest requests. SQLite's own lock still decides (for
    # other processes too), so a thread that waits too long here just goes on to it.
    writer = threading.Lock()

    @event.listens_for(engine, "begin")
    def _on_begin(connection: Connection) -> None:
        connection.info["holds_writer"] = writer.acquire(timeout=BUSY_TIMEOUT_S)
        try:
            connection.exec_driver_sql("BEGIN IMMEDIATE")
        except BaseException:
            _release(connection)
            raise

    def _release(connection: Connection) -> None:
        if connection.info.pop("holds_writer", False):
            writer.release()

    event.listen(engine, "commit", _release)
    event.listen(engine, "rollback", _release)

    @event.listens_for(engine, "checkin")
    def _on_checkin(_dbapi_connection: Any, record: Any) -> None:
        # A safety net: a connection back in the pool never keeps the lock.
        if record.info.pop("holds_writer", False):
            writer.release()

    return engine


def session_factory(engine: Engine) -> sessionmaker[Session]:
    """Sessions whose objects stay readable after commit without touching the database again."""
    return sessionmaker(engine, expire_on_commit=False)


def alembic_config(url: str) -> Config:
    """The Alembic configuration for `url`, without reading alembic.ini or touching logging."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    # Passed as an attribute, not an ini option: ini values treat "%" in passwords specially.
    config.attributes["url"] = url
    return config


def migrate(url: str) -> None:
    """Bring the database at `url` to the newest schema (Alembic `upgrade head`)."""
    command.upgrade(alembic_config(url), "head")

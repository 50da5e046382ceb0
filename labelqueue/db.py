"""Engines, sessions and schema migration for the queue database.

SQLite (the default, one file under the data directory) and PostgreSQL (`postgresql+psycopg://`)
run the same code. On SQLite a transaction that may write starts with BEGIN IMMEDIATE: it takes
the write lock up front, waiting up to the busy timeout, so two writers queue instead of one
failing with "database is locked" when its read transaction tries to become a write. Writers do
not overlap, so keep them short: every queue operation commits before it returns.

Read-only work (`labelqueue.transaction.reading`) asks for the `READ_ONLY` execution option
instead: on SQLite its transaction begins DEFERRED and `query_only`, and takes no lock at all,
since WAL lets readers run beside the one writer on a snapshot of their own.
"""

from __future__ import annotations

import itertools
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import closing, contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.util import CommandError
from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import Connection, make_url
from sqlalchemy.exc import ArgumentError, DBAPIError, NoSuchModuleError
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
        raise ValueError(
            f"{mask_url(url)!r} is not a database URL this app can open; use {VALID_URLS}"
        ) from None
    if parsed.get_backend_name() not in ("sqlite", "postgresql"):
        raise ValueError(
            f"{parsed.get_backend_name()} databases are not supported; use {VALID_URLS}"
        )
    return url


SECRET_QUERY_KEYS = ("password", "sslpassword")
"""query parameters of a database URL that hold a secret (libpq reads a password there too)"""


def mask_url(url: str) -> str:
    """`url` with its password (and any password query parameter) shown as `***`: the form every
    log line, hint and error message uses, so no secret reaches a log, a terminal or a file."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return url.split("@")[-1] if "@" in url else url
    hidden = {key: "***" for key in parsed.query if key in SECRET_QUERY_KEYS}
    if hidden:
        parsed = parsed.update_query_dict(hidden)
    return parsed.render_as_string(hide_password=True).replace("%2A%2A%2A", "***")


def url_has_secret(url: str) -> bool:
    """Whether `url` carries a password (in its user part or its query)."""
    try:
        parsed = make_url(url)
    except (ArgumentError, ValueError):
        return "@" in url
    return parsed.password is not None or any(key in parsed.query for key in SECRET_QUERY_KEYS)


def read_url_file(path: str | Path) -> str:
    """The database URL kept in the file `path` (its first line that is neither empty nor a
    `#` comment). Like libpq with a password file, a file that other users may read is refused.
    ValueError naming the file and the problem."""
    try:
        mode = Path(path).stat().st_mode
        lines = Path(path).read_text().splitlines()
    except OSError as err:
        raise ValueError(f"database URL file {path}: {err.strerror or err}") from None
    if mode & 0o077:
        raise ValueError(f"database URL file {path} may be read by other users (mode "
                         f"{mode & 0o777:o}); chmod 600 {path}")
    for line in lines:
        if line.strip() and not line.lstrip().startswith("#"):
            return line.strip()
    raise ValueError(f"database URL file {path} holds no URL")


def database_url(url: str | None, url_file: str | None,
                 environ: Mapping[str, str] | None = None) -> str | None:
    """The queue's URL from a command's `--database-url` or `--database-url-file` (not both),
    else from the environment: SEPOA_DATABASE_URL, else the file named by
    SEPOA_DATABASE_URL_FILE. None when none is given. ValueError for both flags, or a file that
    cannot be used (`read_url_file`)."""
    environ = os.environ if environ is None else environ
    if url and url_file:
        raise ValueError("give --database-url or --database-url-file, not both")
    if url_file:
        return read_url_file(url_file)
    if url:
        return url
    if environ.get("SEPOA_DATABASE_URL"):
        return environ["SEPOA_DATABASE_URL"]
    if environ.get("SEPOA_DATABASE_URL_FILE"):
        return read_url_file(environ["SEPOA_DATABASE_URL_FILE"])
    return None


BUSY_TIMEOUT_S = 30.0
READ_ONLY = "labelqueue_read_only"
"""the connection execution option that marks a read-only transaction (see `reading`)"""
MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"


class _SQLiteConnection(sqlite3.Connection):
    """A pysqlite connection that hands its engine's writer lock on after COMMIT or ROLLBACK.

    SQLAlchemy's commit and rollback events fire before the statement; releasing the lock there
    let the next writer's BEGIN IMMEDIATE meet SQLite's lock still held and sleep in SQLite's
    busy handler (1, 2, 5, ... ms). Here the lock is handed on once SQLite has let go too.
    """

    writer: threading.Lock | None = None
    holds_writer = False
    query_only = False

    def set_query_only(self, on: bool) -> None:
        if self.query_only != on:
            self.execute(f"PRAGMA query_only={'ON' if on else 'OFF'}")
            self.query_only = on

    def commit(self) -> None:
        self._release_after(super().commit)

    def rollback(self) -> None:
        self._release_after(super().rollback)

    def close(self) -> None:
        self._release_after(super().close)

    def _release_after(self, end: Callable[[], None]) -> None:
        try:
            end()
        finally:
            self.release_writer()

    def release_writer(self) -> None:
        if self.holds_writer and self.writer is not None:
            self.holds_writer = False
            self.writer.release()


class WriterBusy(Exception):
    """Another thread or process holds SQLite's write lock, and the caller asked not to wait
    (`without_waiting`): nothing has run in the transaction, so the work can go elsewhere."""


_NO_WAIT: ContextVar[bool] = ContextVar("labelqueue_no_wait", default=False)


@contextmanager
def without_waiting() -> Iterator[None]:
    """In the block, a transaction that may write begins only if SQLite's write lock is free at
    once, and raises WriterBusy otherwise (on PostgreSQL it begins as usual). For callers that
    must not block, such as an event loop, which then hand the work to a thread that may."""
    token = _NO_WAIT.set(True)
    try:
        yield
    finally:
        _NO_WAIT.reset(token)


RETRY_S = (0.0002, 0.0005, 0.001, 0.002)
"""the waits between tries of BEGIN IMMEDIATE while another process holds SQLite's write lock
(then the last, over and over)"""


def _try_begin_immediate(dbapi_connection: _SQLiteConnection) -> bool:
    """BEGIN IMMEDIATE once, without waiting: False when another process holds the lock."""
    dbapi_connection.execute("PRAGMA busy_timeout=0")
    try:
        dbapi_connection.execute("BEGIN IMMEDIATE")
        return True
    except sqlite3.OperationalError as error:
        if "database is locked" not in str(error):
            raise
        return False
    finally:
        dbapi_connection.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")


def _begin_immediate(dbapi_connection: _SQLiteConnection) -> None:
    """BEGIN IMMEDIATE, tried again after `RETRY_S` while another process (a worker) holds the
    write lock, for up to `BUSY_TIMEOUT_S`. SQLite's own busy handler sleeps 1, 2, 5, 10, 15,
    20, 25, ... 100 ms between tries, so a 5 ms transaction of the worker cost a waiting server
    thread 8 ms, and a 30 ms one 53 ms, while this process's other writers queued behind it.
    A try costs microseconds: it goes to the driver directly, not through SQLAlchemy."""
    deadline = time.monotonic() + BUSY_TIMEOUT_S
    dbapi_connection.execute("PRAGMA busy_timeout=0")
    try:
        for attempt in itertools.count():
            try:
                dbapi_connection.execute("BEGIN IMMEDIATE")
                return
            except sqlite3.OperationalError as error:
                if "database is locked" not in str(error) or time.monotonic() > deadline:
                    raise
            time.sleep(RETRY_S[min(attempt, len(RETRY_S) - 1)])
    finally:
        dbapi_connection.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")


def make_engine(
    url: str, *, foreign_keys: bool = True, background_checkpoints: bool = False
) -> Engine:
    """An engine for `url`; on SQLite with WAL, a busy timeout, foreign keys, BEGIN IMMEDIATE for
    transactions that may write and a deferred, lock-free BEGIN for `READ_ONLY` ones.

    `foreign_keys=False` is for migrations only: SQLite's batch mode recreates tables that
    others reference, which enforcement would refuse.

    `background_checkpoints` (SQLite): the engine's commits never copy the WAL back into the
    database file; a thread of its own does, twice a second (`Checkpointer`). Otherwise SQLite
    does it in whichever commit finds the WAL over 1 000 pages: 13 ms of copying and syncing
    that the server's event loop spent blocked, every 70 labels or so (benchmarks/README.md).
    """
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(parsed, pool_pre_ping=True)

    database = parsed.database or ""
    a_file = database not in ("", ":memory:") and not database.startswith("file:")
    if a_file:
        Path(database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(parsed, connect_args={"factory": _SQLiteConnection})
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
        assert isinstance(dbapi_connection, _SQLiteConnection)
        read_only = bool(connection.get_execution_options().get(READ_ONLY))
        begin_sqlite(dbapi_connection, read_only=read_only)

    return engine


class Checkpointer:
    """A daemon thread that copies a SQLite database's WAL back into its file every `seconds`,
    with PASSIVE checkpoints: they wait for no reader or writer, and their copying and syncing
    run in SQLite's C code, outside the GIL. Other processes' engines keep SQLite's own
    checkpoints at commit."""

    def __init__(self, database: str, seconds: float = 0.5):
        self.database = database
        self.seconds = seconds
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sqlite-checkpoint", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        connection: sqlite3.Connection | None = None
        try:
            while not self._stop.wait(self.seconds):
                try:
                    if connection is None:
                        connection = sqlite3.connect(self.database, check_same_thread=False)
                        connection.execute(f"PRAGMA busy_timeout={int(BUSY_TIMEOUT_S * 1000)}")
                    connection.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                except sqlite3.Error:  # e.g. the file went away; try again on a new connection
                    if connection is not None:
                        connection.close()
                    connection = None
        finally:
            if connection is not None:
                connection.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def begin_sqlite(dbapi_connection: _SQLiteConnection, *, read_only: bool) -> None:
    """Begin a transaction on a connection of `make_engine`'s SQLite engines: deferred and
    query-only when `read_only`, else BEGIN IMMEDIATE behind the engine's writer lock (at once
    or WriterBusy inside `without_waiting`). SQLAlchemy's begin runs it; so does
    `labelqueue.transaction.driver_transaction`, which begins on the driver's connection."""
    if read_only:
        # A write here fails at once, rather than racing for the lock mid-transaction.
        dbapi_connection.set_query_only(True)
        dbapi_connection.execute("BEGIN")
        return
    dbapi_connection.set_query_only(False)
    writer = dbapi_connection.writer
    assert writer is not None, "a connection of make_engine's engines"
    if _NO_WAIT.get():
        dbapi_connection.holds_writer = writer.acquire(blocking=False)
        if not dbapi_connection.holds_writer:
            raise WriterBusy("another thread of this process is writing")
        if not _try_begin_immediate(dbapi_connection):
            dbapi_connection.release_writer()
            raise WriterBusy("another process holds SQLite's write lock")
        return
    dbapi_connection.holds_writer = writer.acquire(timeout=BUSY_TIMEOUT_S)
    try:
        _begin_immediate(dbapi_connection)
    except BaseException:
        dbapi_connection.release_writer()
        raise


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


def schema_revisions(url: str) -> tuple[str | None, str | None]:
    """The database's schema revision (None before any migration) and the newest this version
    of the code knows, read without changing anything."""
    from alembic.runtime.migration import MigrationContext
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(alembic_config(url)).get_current_head()
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            current = MigrationContext.configure(connection).get_current_revision()
    finally:
        engine.dispose()
    return current, head


def sqlite_file(url: str) -> str | None:
    """The SQLite file `url` names, or None (another database, in memory, or a `file:` URI)."""
    parsed = make_url(url)
    database = parsed.database or ""
    if parsed.get_backend_name() != "sqlite" or database in ("", ":memory:") \
            or database.startswith("file:"):
        return None
    return database


def integrity_problem(url: str) -> str | None:
    """What SQLite's `PRAGMA quick_check` finds wrong with the database file at `url` (its first
    finding, and how many more), or why the file cannot be read as a database; None when it
    finds nothing, and for a file that does not exist or a database that is not SQLite. The
    check reads every page once (about a second per few hundred MB)."""
    path = sqlite_file(url)
    if path is None or not os.path.isfile(path):
        return None
    try:
        with closing(sqlite3.connect(path, timeout=BUSY_TIMEOUT_S)) as connection:
            rows = connection.execute("PRAGMA quick_check").fetchall()
    except sqlite3.DatabaseError as error:  # "file is not a database", "... is malformed"
        return str(error)
    found = [line for (text,) in rows for line in str(text).splitlines()
             if line.strip() and line != "ok" and not line.startswith("***")]
    if not found:
        return None
    return found[0] + (f" (and {len(found) - 1} more)" if len(found) > 1 else "")


def check_database(url: str, *, writable: bool = False) -> None:
    """Refuse, with a ValueError of one line, a database that cannot be used: a SQLite file the
    integrity check finds damaged, and with `writable` (a server's start) one that cannot be
    migrated to the newest schema or written (a read-only file, a replica). `writable` also
    migrates it."""
    problem = integrity_problem(url)
    if problem is not None:
        raise ValueError(f"the queue database {sqlite_file(url)} is damaged (PRAGMA "
                         f"quick_check: {problem}); restore it from a backup")
    if not writable:
        return
    try:
        migrate(url)
        engine = make_engine(url)
        try:
            with engine.connect() as connection, connection.begin() as probe:
                # A write that changes nothing, rolled back: refused on a read-only database.
                connection.exec_driver_sql(
                    "UPDATE alembic_version SET version_num = version_num")
                probe.rollback()
        finally:
            engine.dispose()
    except DBAPIError as error:
        first = str(error.orig or error).strip().splitlines()[0]
        raise ValueError(f"cannot use the queue database {mask_url(url)}: {first}") from None
    except CommandError as error:  # e.g. a schema newer than this version knows
        raise ValueError(f"cannot migrate the queue database {mask_url(url)}: {error}") from None

"""SQLite's one writer, shared fairly: a transaction that may write starts with BEGIN IMMEDIATE
behind a lock of the engine's own, handed on as soon as SQLite lets go; read-only transactions
(`READ_ONLY`) begin deferred and query-only and take no lock, since WAL lets readers run beside
the writer on a snapshot of their own. A thread copies the WAL back into the file
(`Checkpointer`) so that no commit on the server's event loop does it.
"""

from __future__ import annotations

import itertools
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

BUSY_TIMEOUT_S = 30.0
READ_ONLY = "labelqueue_read_only"
"""the connection execution option that marks a read-only transaction (see `reading`)"""


class SQLiteConnection(sqlite3.Connection):
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


def _try_begin_immediate(dbapi_connection: SQLiteConnection) -> bool:
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


def _begin_immediate(dbapi_connection: SQLiteConnection) -> None:
    """BEGIN IMMEDIATE, tried again after `RETRY_S` while another process (a worker) holds the
    write lock, for up to `BUSY_TIMEOUT_S`: SQLite's own busy handler sleeps up to 100 ms between
    tries, far longer than a worker's transaction holds the lock. A try costs microseconds: it
    goes to the driver directly, not through SQLAlchemy."""
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


def begin_sqlite(dbapi_connection: SQLiteConnection, *, read_only: bool) -> None:
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

"""The queue database's schema and health: Alembic migrations to the newest schema, the
revision a database is at, and the checks that refuse a database that cannot be used (a file
that is no queue, damaged, read-only, newer than this code)."""

from __future__ import annotations

import mmap
import os
import sqlite3
from contextlib import closing
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.util import CommandError
from sqlalchemy.engine import make_url
from sqlalchemy.exc import DBAPIError

from labelqueue.db_url import mask_url
from labelqueue.engine import make_engine
from labelqueue.models import Base
from labelqueue.sqlite_writer import BUSY_TIMEOUT_S

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"


def alembic_config(url: str) -> Config:
    """The Alembic configuration for `url`, without reading alembic.ini or touching logging."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    # Passed as an attribute, not an ini option: ini values treat "%" in passwords specially.
    config.attributes["url"] = url
    return config


def migrate(url: str) -> None:
    """Bring the database at `url` to the newest schema (Alembic `upgrade head`); a file that is
    no queue is refused (`check_queue_file`), its tables never mixed with the queue's."""
    check_queue_file(url)
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


QUEUE_SCHEMA = b"CREATE TABLE alembic_version"
"""a queue's first table as its file keeps it, still there when the file's header is damaged"""
ELSEWHERE = "give the queue's own file, or a path where there is none yet for a new queue"


def check_queue_file(url: str) -> None:
    """Refuse, with a ValueError of one line, an existing SQLite file `url` names that is no
    queue: not an SQLite database (no SQLite header, and no queue's schema, which a queue whose
    header is damaged still holds: `integrity_problem` finds that), or an SQLite database with
    tables, none of them the queue's. A file with no tables yet is one a queue is made in."""
    path = sqlite_file(url)
    if path is None or not os.path.isfile(path):
        return
    try:
        with closing(sqlite3.connect(path, timeout=BUSY_TIMEOUT_S)) as connection:
            tables = {name for (name,) in connection.execute(
                "SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.DatabaseError as error:
        if error.sqlite_errorcode == sqlite3.SQLITE_NOTADB and not _holds_queue_schema(path):
            raise ValueError(f"{path} is not an SQLite database: {ELSEWHERE}") from None
        return  # damaged (or busy): integrity_problem says how
    if tables and not tables & {"alembic_version", *Base.metadata.tables}:
        raise ValueError(f"{path} is an SQLite database but not a sepoa queue (no queue "
                         f"tables): {ELSEWHERE}")


def _holds_queue_schema(path: str) -> bool:
    # Read only once SQLite has found no database header: closing any descriptor of a file
    # drops every POSIX lock this process holds on it, so reading a live queue's bytes beside
    # its open connections would let another connection write under them (a corrupted file).
    with open(path, "rb") as file, mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:
        return data.find(QUEUE_SCHEMA) >= 0


def check_database(url: str, *, writable: bool = False) -> None:
    """Refuse, with a ValueError of one line, a database that cannot be used: a SQLite file that
    is no queue (`check_queue_file`) or that the integrity check finds damaged, and with
    `writable` (a server's start) one that cannot be migrated to the newest schema or written (a
    read-only file, a replica). `writable` also migrates it."""
    check_queue_file(url)
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

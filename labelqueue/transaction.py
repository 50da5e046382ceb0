"""How every queue operation runs: one transaction, conditional updates, detached results.

Every operation runs in one transaction on the session it is given and commits before it
returns; when it raises, it has rolled back and changed nothing. Give it a session with no
unfinished work of its own. The rows it returns are detached snapshots: reading them never
touches the database again (so never reopens a transaction), and changing them changes nothing.

Races are decided by the database: each state change is a conditional UPDATE whose WHERE clause
restates the condition it relies on, and the number of rows it changed says who won. On SQLite
the writing transactions also run one at a time (see `labelqueue.sqlite_writer`); on PostgreSQL
a losing UPDATE waits for the winner, re-checks its WHERE on the new row and changes nothing.

Operations that only read run in `reading(session)`: on SQLite a deferred, query-only
transaction that takes no lock, so it runs beside a writer (WAL) and never makes one wait.

Two tiers, one rule: every operation runs in the ORM session (`transaction`, `reading`), except
the label API's lease, submit and their gold checks, which run `Prepared` statements in a
`driver_transaction` (docs/ARCHITECTURE.md says why, and what a new hot statement must do).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from functools import cache
from typing import Any, TypeVar, cast

from sqlalchemy import CursorResult, Engine, Update
from sqlalchemy.orm import ClassManager, Session, class_mapper

from labelqueue.errors import NotFound
from labelqueue.models import Base
from labelqueue.prepared import DriverConnection, traced
from labelqueue.sqlite_writer import READ_ONLY, begin_sqlite

M = TypeVar("M", bound=Base)


@contextmanager
def transaction(session: Session) -> Iterator[None]:
    """Commit when the block ends; roll back when the block or the commit raises."""
    try:
        yield
        session.commit()
    except BaseException:
        session.rollback()
        raise


@contextmanager
def reading(session: Session) -> Iterator[None]:
    """A read-only transaction for the block, ended when it ends (rows read stay readable).

    On SQLite it begins DEFERRED, takes no lock and refuses writes (`PRAGMA query_only`); on
    PostgreSQL it is a plain transaction. In a session whose transaction is already open, the
    block joins it and commits it.
    """
    if not session.in_transaction():
        session.connection(execution_options={READ_ONLY: True})
    try:
        yield
    finally:
        session.commit()


@contextmanager
def driver_transaction(session: Session) -> Iterator[DriverConnection]:
    """One writing transaction on a driver connection from the session's engine pool, for
    `Prepared` statements: committed when the block ends, rolled back when it raises.

    SQLAlchemy's transaction is skipped (on SQLite the same begin as theirs,
    `labelqueue.sqlite_writer.begin_sqlite`; psycopg begins at the first statement), and so is its
    Connection unless something traces the engine (`prepared.traced`): on the label API's hot
    path they cost more than the statements. A session with a transaction open, or bound to a
    connection rather than an engine, runs the block in its own transaction instead.
    """
    bind = session.get_bind()
    if session.in_transaction() or not isinstance(bind, Engine):
        with transaction(session):
            yield DriverConnection.under(session.connection())
        return
    tracer = bind.connect() if traced(bind) else None
    pooled = bind.raw_connection() if tracer is None else tracer.connection
    try:
        if bind.dialect.name == "sqlite":
            begin_sqlite(pooled.dbapi_connection, read_only=False)  # type: ignore[arg-type]
        connection = DriverConnection(pooled.dbapi_connection, bind.dialect, pooled, tracer)
        try:
            yield connection
        except BaseException:
            pooled.rollback()
            raise
        try:
            pooled.commit()
        except bind.dialect.loaded_dbapi.Error as error:
            pooled.rollback()
            raise connection.wrapped(error, "COMMIT", None) from error
    finally:
        (pooled if tracer is None else tracer).close()


def detach(session: Session, *rows: Base) -> None:
    """Flush, then detach `rows`: a later rollback in this session cannot expire them."""
    session.flush()
    for row in rows:
        session.expunge(row)


def changed(session: Session, statement: Update) -> int:
    """Run a conditional UPDATE; the number of rows it changed."""
    # No in-memory synchronisation: it would expire attributes, and reading an expired one
    # silently opens a new transaction. Operations re-read what they return instead.
    result = session.execute(statement, execution_options={"synchronize_session": False})
    return cast(CursorResult[Any], result).rowcount


def get_row(session: Session, model: type[M], ident: Any) -> M:
    """The row as stored now (not a stale copy from this session), or NotFound."""
    row = session.get(model, ident, populate_existing=True)
    if row is None:
        raise NotFound(f"{model.__name__.lower()} {ident} does not exist")
    return row


@cache
def _manager(model: type[Base]) -> ClassManager[Any]:
    return class_mapper(model).class_manager  # configures the mappers once


def snapshot(model: type[M], values: Mapping[Any, Any]) -> M:
    """A `model` row holding `values` (column name -> value), in no session: a detached-style
    snapshot built from a Core result the way the ORM loads rows, without per-attribute events.
    """
    row = cast(M, _manager(model).new_instance())
    row.__dict__.update(values)
    return row

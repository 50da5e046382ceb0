"""How every queue operation runs: one transaction, conditional updates, detached results.

Every operation runs in one transaction on the session it is given and commits before it
returns; when it raises, it has rolled back and changed nothing. Give it a session with no
unfinished work of its own. The rows it returns are detached snapshots: reading them never
touches the database again (so never reopens a transaction), and changing them changes nothing.

Races are decided by the database: each state change is a conditional UPDATE whose WHERE clause
restates the condition it relies on, and the number of rows it changed says who won. On SQLite
the transactions also run one at a time (see `labelqueue.db`); on PostgreSQL a losing UPDATE
waits for the winner, re-checks its WHERE on the new row and changes nothing.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any, TypeVar, cast

from sqlalchemy import CursorResult, Update
from sqlalchemy.orm import Session

from labelqueue.errors import NotFound
from labelqueue.models import Base

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

"""`without_waiting`: a write that would wait for SQLite's lock refuses to start instead, having
changed nothing, so an event loop can hand it to a thread; it writes as usual when the lock is
free, and on PostgreSQL it changes nothing."""

from __future__ import annotations

import threading

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from labelqueue import (
    QueryStatus,
    TeacherKind,
    WriterBusy,
    create_labeller,
    lease_next_query,
    make_engine,
    push_queries,
    without_waiting,
)
from labelqueue.models import Query


def statuses(session: Session) -> list[QueryStatus]:
    rows = [q.status for q in session.query(Query).order_by(Query.id)]
    session.commit()
    return rows


def test_a_free_lock_lets_the_write_run(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    with without_waiting():
        leased = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert leased is not None and statuses(session) == [QueryStatus.LEASED]


def test_another_process_holding_the_lock_makes_the_write_refuse_to_start(
    engine: Engine, url: str, session: Session
) -> None:
    if engine.dialect.name != "sqlite":
        pytest.skip("SQLite's write lock")
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    other = make_engine(url)  # its own in-process lock: as another process, SQLite's lock only
    try:
        with other.connect() as holder, holder.begin():
            with without_waiting(), pytest.raises(WriterBusy, match="another process"):
                lease_next_query(session, labeller_id=alice.id, run_id=run.id)
            # Without the block it would wait; the lock is still held, and nothing changed.
        assert statuses(session) == [QueryStatus.PENDING]
        assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
    finally:
        other.dispose()


def test_another_thread_writing_makes_the_write_refuse_to_start(
    engine: Engine, session: Session
) -> None:
    if engine.dialect.name != "sqlite":
        pytest.skip("SQLite's write lock")
    run = running_run(session, teacher=TeacherKind.HUMAN)
    push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    holding, release = threading.Event(), threading.Event()

    def write_slowly() -> None:
        with engine.connect() as connection, connection.begin():
            holding.set()
            release.wait(timeout=30)

    writer = threading.Thread(target=write_slowly)
    writer.start()
    try:
        assert holding.wait(timeout=30)
        with without_waiting(), pytest.raises(WriterBusy, match="another thread"):
            lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    finally:
        release.set()
        writer.join(timeout=30)
    assert statuses(session) == [QueryStatus.PENDING]
    with without_waiting():
        assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None

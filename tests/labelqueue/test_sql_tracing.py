"""The label API's hot statements (lease, submit, gold checks) run on the driver's connection,
yet tracing sees them as it sees SQLAlchemy's own: an engine's cursor-execute listeners are
called with each, and its logger (`echo`) logs them; on each database."""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

import pytest
from queue_helpers import query_spec
from sqlalchemy import Engine, event
from sqlalchemy.orm import Session

from labelqueue import (
    claim_run,
    create_labeller,
    create_run,
    lease_next_query,
    push_queries,
    submit_label,
)


@pytest.fixture
def leasable(session: Session) -> tuple[int, int]:
    """A running run with an ordinary query and a gold pair, gold due by the second answer
    (half the answers, whatever the schedule's offset); (its labeller's id, its id)."""
    create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=10,
               config={"feedback.gold_rate": 0.5, "feedback.gold_min_accuracy": 0.5},
               teacher="scripted")
    run = claim_run(session, worker_id="w")
    assert run is not None
    push_queries(session, run_id=run.id,
                 queries=[query_spec(0), query_spec(1) | {"gold": True}])
    labeller, _ = create_labeller(session, name="alice")
    return labeller.id, run.id


def lease_and_answer(session: Session, leasable: tuple[int, int]) -> None:
    """Lease and answer the ordinary query, then the gold pair."""
    labeller_id, run_id = leasable
    for gold in (False, True):
        query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
        assert query is not None and query.gold is gold
        assert query is not None
        submit_label(session, query_id=query.id, labeller_id=labeller_id, choice="left",
                     left_is_first=True, shown_at=datetime.now(UTC), source="scripted")


def test_cursor_execute_listeners_see_every_hot_statement(
    engine: Engine, session: Session, leasable: tuple[int, int]
) -> None:
    seen: list[tuple[str, Any]] = []
    after: list[str] = []

    def before_cursor_execute(conn: Any, cursor: Any, statement: str, parameters: Any,
                              context: Any, executemany: bool) -> None:
        assert conn.engine is engine and cursor is not None
        seen.append((" ".join(statement.split()).upper(), parameters))

    def after_cursor_execute(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        after.append(statement)

    event.listen(engine, "before_cursor_execute", before_cursor_execute)
    event.listen(engine, "after_cursor_execute", after_cursor_execute)
    try:
        lease_and_answer(session, leasable)
    finally:
        event.remove(engine, "before_cursor_execute", before_cursor_execute)
        event.remove(engine, "after_cursor_execute", after_cursor_execute)
    statements = [sql for sql, _ in seen]
    leases = [sql for sql in statements if sql.startswith("UPDATE QUERIES SET STATUS")
              and "LEASE_HOLDER" in sql and "RETURNING" in sql]
    answers = [sql for sql in statements if sql.startswith("INSERT INTO LABELS")]
    gold_checks = [sql for sql in statements if "FROM LABELLER_PAUSES" in sql]
    assert len(leases) == 2 and len(answers) == 2 and gold_checks, statements
    assert len(after) == len(seen)
    # The values the driver got, as the listener sees them: the labeller's id among them.
    [(_, values)] = [(sql, p) for sql, p in seen if sql.startswith("INSERT INTO LABELS")][:1]
    assert leasable[0] in (values.values() if isinstance(values, dict) else values)


def test_echo_logs_the_hot_statements(engine: Engine, session: Session, leasable: tuple[int, int],
                                      caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.INFO, logger="sqlalchemy.engine"):
        lease_and_answer(session, leasable)
    logged = [" ".join(r.getMessage().split()).upper() for r in caplog.records
              if r.name.startswith("sqlalchemy.engine")]
    assert any(line.startswith("INSERT INTO LABELS") for line in logged), logged
    assert any(line.startswith("UPDATE QUERIES SET STATUS") for line in logged)

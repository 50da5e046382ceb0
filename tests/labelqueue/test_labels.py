"""Answers are stored once per labeller and query, and the trainer takes each exactly once."""

from __future__ import annotations

from datetime import UTC, datetime

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    Choice,
    Label,
    LabelSource,
    NotFound,
    Preferred,
    Run,
    consume_labels,
    create_labeller,
    labels_for_queries,
    lease_next_query,
    push_queries,
    submit_label,
)
from labelqueue.labels import preferred_segment


@pytest.mark.parametrize(
    ("choice", "left_is_first", "preferred"),
    [
        (Choice.LEFT, True, Preferred.FIRST),
        (Choice.LEFT, False, Preferred.SECOND),
        (Choice.RIGHT, True, Preferred.SECOND),
        (Choice.RIGHT, False, Preferred.FIRST),
        (Choice.EQUAL, True, Preferred.EQUAL),
        (Choice.EQUAL, False, Preferred.EQUAL),
        (Choice.CANT_TELL, True, None),
        (Choice.SKIP, False, None),
    ],
)
def test_the_screen_choice_maps_to_the_preferred_segment(
    session: Session, choice: Choice, left_is_first: bool, preferred: Preferred | None
) -> None:
    assert preferred_segment(choice, left_is_first) == preferred
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    label, created = submit_label(
        session,
        query_id=query_id,
        labeller_id=alice.id,
        choice=choice,
        left_is_first=left_is_first,
    )
    assert created and label.preferred == preferred and label.choice is choice
    stored = session.get(Label, label.id)
    assert stored is not None and stored.preferred == preferred


def test_a_repeated_submit_returns_the_stored_label(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    shown = datetime(2026, 1, 2, 3, 4, 5, tzinfo=UTC)
    first, created = submit_label(
        session,
        query_id=query_id,
        labeller_id=alice.id,
        choice="right",
        left_is_first=False,
        shown_at=shown,
    )
    assert created and first.shown_at == shown and first.source is LabelSource.HUMAN
    assert first.answered_at.tzinfo is not None and first.consumed_at is None
    # The lease is gone, yet a retried request (even with another answer) gets the stored label.
    again, created = submit_label(
        session, query_id=query_id, labeller_id=alice.id, choice="left", left_is_first=True
    )
    assert not created and again.id == first.id and again.choice is Choice.RIGHT
    assert session.scalar(select(func.count()).select_from(Label)) == 1
    assert session.get(Run, run.id).labels_used == 1  # type: ignore[union-attr]


def test_every_answer_counts_against_the_budget(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    teacher, _ = create_labeller(session, name="teacher")
    for query_id, choice in zip(ids, ["skip", "cant_tell", "equal"], strict=True):
        leased = lease_next_query(session, labeller_id=teacher.id, run_id=run.id)
        assert leased is not None and leased.id == query_id
        submit_label(
            session,
            query_id=query_id,
            labeller_id=teacher.id,
            choice=choice,
            left_is_first=True,
            source="scripted",
        )
    assert session.get(Run, run.id, populate_existing=True).labels_used == 3  # type: ignore[union-attr]


def label_all(session: Session, run_id: int, labeller_id: int) -> list[int]:
    label_ids = []
    while (query := lease_next_query(session, labeller_id=labeller_id, run_id=run_id)) is not None:
        label, _ = submit_label(
            session, query_id=query.id, labeller_id=labeller_id, choice="left", left_is_first=True
        )
        label_ids.append(label.id)
    return label_ids


def test_labels_are_consumed_once_and_can_be_read_again_by_query(session: Session) -> None:
    run = running_run(session)
    other = running_run(session, worker_id="w2")
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(4)])
    push_queries(session, run_id=other.id, queries=[query_spec(0)])
    teacher, _ = create_labeller(session, name="teacher")
    label_all(session, other.id, teacher.id)

    for query_id in ids[:2]:
        lease_next_query(session, labeller_id=teacher.id, run_id=run.id)
        submit_label(
            session, query_id=query_id, labeller_id=teacher.id, choice="left", left_is_first=True
        )
    taken = consume_labels(session, run_id=run.id)
    assert [label.query_id for label in taken] == ids[:2]
    assert all(label.consumed_at is not None for label in taken)
    assert consume_labels(session, run_id=run.id) == []

    label_all(session, run.id, teacher.id)
    assert [label.query_id for label in consume_labels(session, run_id=run.id)] == ids[2:]

    # A trainer resumed from a checkpoint taken before it consumed re-reads by query id.
    again = labels_for_queries(session, query_ids=ids)
    assert [label.query_id for label in again] == ids
    assert labels_for_queries(session, query_ids=[]) == []
    with pytest.raises(NotFound):
        consume_labels(session, run_id=999)


def test_a_consumer_that_dies_before_committing_loses_nothing(
    sessions: sessionmaker[Session],
) -> None:
    with sessions() as session:
        run = running_run(session)
        push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
        teacher, _ = create_labeller(session, name="teacher")
        label_ids = label_all(session, run.id, teacher.id)

    with sessions() as dying:

        def lose_connection() -> None:
            raise ConnectionError("killed")

        dying.commit = lose_connection  # type: ignore[method-assign]
        with pytest.raises(ConnectionError):
            consume_labels(dying, run_id=run.id)

    with sessions() as session:
        assert [label.id for label in consume_labels(session, run_id=run.id)] == label_ids


def test_returned_rows_stay_readable_after_a_failed_operation(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    query = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    with pytest.raises(NotFound):
        consume_labels(session, run_id=999)  # rolls the session back
    # Reading a returned row neither fails nor opens a transaction that would hold SQLite's lock.
    assert query is not None and query.id == query_id and query.lease_holder == alice.id
    assert not session.in_transaction()

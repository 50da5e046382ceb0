"""Answers are stored once per labeller and query, and the trainer takes each exactly once."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    Label,
    LabelSource,
    NotFound,
    Query,
    QueryStatus,
    Revoked,
    Run,
    RunClosed,
    RunStatus,
    claim_run,
    consume_labels,
    create_labeller,
    finish_run,
    labels_for_queries,
    lease_next_query,
    push_queries,
    set_labeller_active,
    set_run_status,
    submit_answer,
    submit_label,
)
from runvocab.answers import Answer, Click, answer_of_click


@pytest.mark.parametrize(
    ("choice", "left_is_first", "preferred"),
    [
        (Click.LEFT, True, Answer.FIRST),
        (Click.LEFT, False, Answer.SECOND),
        (Click.RIGHT, True, Answer.SECOND),
        (Click.RIGHT, False, Answer.FIRST),
        (Click.EQUAL, True, Answer.EQUAL),
        (Click.EQUAL, False, Answer.EQUAL),
        (Click.CANT_TELL, True, Answer.CANT_TELL),
        (Click.SKIP, False, Answer.SKIP),
    ],
)
def test_the_screen_choice_maps_to_the_preferred_segment(
    session: Session, choice: Click, left_is_first: bool, preferred: Answer
) -> None:
    assert answer_of_click(choice, left_is_first) == preferred
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
    assert created and label.answer == preferred and label.choice is choice
    stored = session.get(Label, label.id)
    assert stored is not None and stored.answer == preferred


@pytest.mark.parametrize("answer", list(Answer))
def test_an_answer_in_segment_terms_is_stored_as_given(session: Session, answer: Answer) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    teacher, _ = create_labeller(session, name="teacher")
    lease_next_query(session, labeller_id=teacher.id, run_id=run.id)
    label, created = submit_answer(session, query_id=query_id, labeller_id=teacher.id,
                                   answer=answer)
    assert created and label.answer is answer and label.source is LabelSource.SCRIPTED
    # On record as if shown with the first segment on the left.
    assert label.left_is_first and answer_of_click(label.choice, True) is answer
    assert session.scalars(select(Query.status).where(Query.id == query_id)).one() == (
        QueryStatus.LABELLED)


def test_a_repeated_submit_returns_the_stored_label(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    shown = datetime.now(UTC)  # after the lease began: stored as given
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
    assert not created and again.id == first.id and again.choice is Click.RIGHT
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


def _stored(session: Session) -> tuple[int, int]:
    """(labels stored, the run's labels_used) of the only run."""
    labels = session.scalar(select(func.count()).select_from(Label))
    used = session.scalars(select(Run.labels_used)).one()
    session.commit()
    return int(labels or 0), used


def test_a_revoked_labeller_cannot_answer_the_query_it_holds(session: Session) -> None:
    run = running_run(session)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    mallory, _ = create_labeller(session, name="mallory")
    bob, _ = create_labeller(session, name="bob")
    assert lease_next_query(session, labeller_id=mallory.id, run_id=run.id) is not None
    set_labeller_active(session, labeller_id=mallory.id, active=False)
    with pytest.raises(Revoked, match="deactivated"):
        submit_label(
            session, query_id=query_id, labeller_id=mallory.id, choice="left", left_is_first=True
        )
    assert _stored(session) == (0, 0)
    # Revoking released the lease: someone else may answer the query at once.
    leased = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert leased is not None and leased.id == query_id


def test_an_answer_after_a_stop_is_refused_and_answers_before_it_are_used_on_requeue(
    session: Session,
) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(0), query_spec(1)])
    alice, _ = create_labeller(session, name="alice")
    bob, _ = create_labeller(session, name="bob")
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
    assert lease_next_query(session, labeller_id=bob.id, run_id=run.id) is not None
    submit_label(session, query_id=ids[0], labeller_id=alice.id, choice="left", left_is_first=True)

    set_run_status(session, run_id=run.id, status=RunStatus.STOPPING)
    for status in ("stopping", "stopped"):
        with pytest.raises(RunClosed, match=f"run {run.id} is {status}"):
            submit_label(
                session, query_id=ids[1], labeller_id=bob.id, choice="right", left_is_first=True
            )
        assert _stored(session) == (1, 1)  # the refused answer spent no budget
        if status == "stopping":
            finish_run(session, run_id=run.id, worker_id="worker-a", status=RunStatus.STOPPED)

    # Requeued and resumed: the round's labels given before the stop are all there.
    set_run_status(session, run_id=run.id, status=RunStatus.QUEUED)
    assert claim_run(session, worker_id="worker-b") is not None
    [kept] = labels_for_queries(session, query_ids=ids)
    assert (kept.query_id, kept.labeller_id, kept.choice) == (ids[0], alice.id, Click.LEFT)


def test_shown_at_is_kept_between_the_lease_and_the_answer(session: Session) -> None:
    run = running_run(session)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(3)])
    alice, _ = create_labeller(session, name="alice")
    skewed = {
        "years ago": datetime(2001, 1, 1, tzinfo=UTC),
        "tomorrow": datetime.now(UTC) + timedelta(days=1),
        "naive, a minute ago": datetime.now(UTC).replace(tzinfo=None) - timedelta(minutes=1),
    }
    for query_id, (why, shown) in zip(ids, skewed.items(), strict=True):
        leased = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
        assert leased is not None and leased.leased_at is not None
        label, _ = submit_label(
            session, query_id=query_id, labeller_id=alice.id, choice="left", left_is_first=True,
            shown_at=shown,
        )
        assert label.shown_at is not None
        assert leased.leased_at <= label.shown_at <= label.answered_at, why
        if why == "years ago":
            assert label.shown_at == leased.leased_at
        if why == "tomorrow":
            assert label.shown_at == label.answered_at
    session.commit()
    stored = session.scalars(select(Query)).all()
    assert all(q.status is QueryStatus.LABELLED and q.leased_at is None for q in stored)

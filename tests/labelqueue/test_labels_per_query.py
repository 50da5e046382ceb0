"""A query that wants k answers goes to k different labellers, once each, and is labelled after
the k-th; every answer counts against the run's budget."""

from __future__ import annotations

from queue_helpers import query_spec, running_run
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    Query,
    QueryStatus,
    Run,
    TeacherKind,
    create_labeller,
    labels_for_queries,
    lease_next_query,
    push_queries,
    submit_label,
)
from runvocab.answers import Answer


def _query(session: Session, query_id: int) -> Query:
    query = session.get(Query, query_id, populate_existing=True)
    assert query is not None
    session.commit()
    return query


def _labels_used(session: Session, run_id: int) -> int:
    run = session.get(Run, run_id, populate_existing=True)
    assert run is not None
    session.commit()
    return run.labels_used


def _answer(session: Session, query_id: int, labeller_id: int, choice: str = "left") -> Label:
    label, created = submit_label(
        session, query_id=query_id, labeller_id=labeller_id, choice=choice, left_is_first=True
    )
    assert created
    return label


def test_a_query_wanting_three_answers_goes_to_three_labellers_once_each(
    session: Session,
) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    [query_id] = push_queries(
        session, run_id=run.id, queries=[query_spec(0, needs_labels=3)]
    )
    assert _query(session, query_id).needs_labels == 3
    people = [create_labeller(session, name=name)[0] for name in ("ann", "bob", "cy", "dee")]

    for n, (person, choice) in enumerate(zip(people[:3], ["left", "right", "left"], strict=True)):
        leased = lease_next_query(session, labeller_id=person.id)
        assert leased is not None and leased.id == query_id, person.name
        # While one person holds it, nobody else gets it (one lease at a time).
        assert lease_next_query(session, labeller_id=people[3].id) is None
        _answer(session, query_id, person.id, choice)
        # Who answered never gets it again, on the run or on any run.
        assert lease_next_query(session, labeller_id=person.id) is None
        assert lease_next_query(session, labeller_id=person.id, run_id=run.id) is None
        query = _query(session, query_id)
        assert query.label_count == n + 1
        if n < 2:
            assert query.status is QueryStatus.PENDING, f"after {n + 1} answers"

    assert _query(session, query_id).status is QueryStatus.LABELLED
    assert lease_next_query(session, labeller_id=people[3].id) is None  # a fourth: nothing left
    assert _labels_used(session, run.id) == 3
    stored = labels_for_queries(session, query_ids=[query_id])
    assert [label.labeller_id for label in stored] == [p.id for p in people[:3]]
    assert [label.answer for label in stored] == [Answer.FIRST, Answer.SECOND, Answer.FIRST]


def test_a_labeller_who_answered_gets_the_next_query_instead(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    first, second = push_queries(
        session, run_id=run.id, queries=[query_spec(i, needs_labels=2) for i in range(2)]
    )
    ann, _ = create_labeller(session, name="ann")
    bob, _ = create_labeller(session, name="bob")
    leased = lease_next_query(session, labeller_id=ann.id, run_id=run.id)
    assert leased is not None and leased.id == first
    _answer(session, first, ann.id)
    # The oldest open query is one ann answered: she gets the next one, bob the oldest.
    leased = lease_next_query(session, labeller_id=ann.id, run_id=run.id)
    assert leased is not None and leased.id == second
    leased = lease_next_query(session, labeller_id=bob.id, run_id=run.id)
    assert leased is not None and leased.id == first
    _answer(session, first, bob.id, "skip")  # a skip is an answer: it counts towards k
    _answer(session, second, ann.id)
    assert _query(session, first).status is QueryStatus.LABELLED
    assert _query(session, second).status is QueryStatus.PENDING
    assert lease_next_query(session, labeller_id=ann.id, run_id=run.id) is None
    assert _labels_used(session, run.id) == 3


def test_a_repeated_submit_is_not_a_second_answer(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0, needs_labels=2)])
    ann, _ = create_labeller(session, name="ann")
    lease_next_query(session, labeller_id=ann.id)
    _answer(session, query_id, ann.id)
    again, created = submit_label(
        session, query_id=query_id, labeller_id=ann.id, choice="right", left_is_first=True
    )
    assert not created and again.answer is Answer.FIRST
    query = _query(session, query_id)
    assert query.label_count == 1 and query.status is QueryStatus.PENDING
    assert _labels_used(session, run.id) == 1


def test_one_answer_per_query_by_default(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    ann, _ = create_labeller(session, name="ann")
    bob, _ = create_labeller(session, name="bob")
    lease_next_query(session, labeller_id=ann.id)
    _answer(session, query_id, ann.id)
    assert _query(session, query_id).status is QueryStatus.LABELLED
    assert lease_next_query(session, labeller_id=bob.id) is None

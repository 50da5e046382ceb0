"""Taking an answer back, on each database: the label is kept withdrawn, the query leased back,
the budget returned; the trainer never reads it; a second answer stands beside it; and the
trainer consuming it first wins."""

from __future__ import annotations

import threading
import time

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import Engine, select, text
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    NotFound,
    QueryStatus,
    TeacherKind,
    UndoRefused,
    cancel_queries,
    claim_run,
    consume_labels,
    create_labeller,
    create_run,
    labels_for_queries,
    lease_next_query,
    push_queries,
    read_run,
    submit_label,
    withdraw_label,
)
from labelqueue.models import Query, Run


def test_a_withdrawn_label_stays_and_a_new_answer_stands_beside_it(session: Session) -> None:
    run = running_run(session, teacher=TeacherKind.HUMAN)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
    label, _ = submit_label(session, query_id=query_id, labeller_id=alice.id, choice="left",
                            left_is_first=True)

    back = withdraw_label(session, query_id=query_id, labeller_id=alice.id)
    assert back.label.id == label.id and back.label.withdrawn_at is not None
    assert back.query.status is QueryStatus.LEASED and back.query.lease_holder == alice.id
    assert back.query.label_count == 0
    assert read_run(session, run_id=run.id).labels_used == 0
    assert labels_for_queries(session, query_ids=[query_id]) == []
    assert consume_labels(session, run_id=run.id) == []
    with pytest.raises(NotFound):  # nothing standing to take back
        withdraw_label(session, query_id=query_id, labeller_id=alice.id)

    again, created = submit_label(session, query_id=query_id, labeller_id=alice.id,
                                  choice="right", left_is_first=True)
    assert created and again.id != label.id
    assert [x.id for x in labels_for_queries(session, query_ids=[query_id])] == [again.id]
    assert [x.id for x in consume_labels(session, run_id=run.id)] == [again.id]
    with pytest.raises(UndoRefused, match="already taken"):
        withdraw_label(session, query_id=query_id, labeller_id=alice.id)
    stored = session.get(Query, query_id)
    assert stored is not None and stored.status is QueryStatus.LABELLED
    session.commit()


def test_a_query_whose_answer_was_taken_back_is_leased_to_that_labeller_again(
    session: Session,
) -> None:
    """The lease skips queries the labeller answered, but not one whose answer it took back."""
    run = running_run(session, teacher=TeacherKind.HUMAN)
    [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
    alice, _ = create_labeller(session, name="alice")
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
    submit_label(session, query_id=query_id, labeller_id=alice.id, choice="left",
                 left_is_first=True)
    assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is None

    withdraw_label(session, query_id=query_id, labeller_id=alice.id, lease_seconds=-1)
    again = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert again is not None and again.id == query_id


def test_consuming_skips_a_label_an_undo_holds_rather_than_wait_for_it(
    url: str, engine: Engine, sessions: sessionmaker[Session]
) -> None:
    """An undo locks its label, then the query and the run; the trainer's take locks the run,
    then the labels. It skips a label an undo holds, so neither waits for the other (PostgreSQL
    would abort one as a deadlock, and the worker's would end the run), and takes it on a later
    call once the undo is refused."""
    if not url.startswith("postgresql"):
        pytest.skip("SQLite's writers take turns: no row locks to order")
    with sessions() as session:
        run = running_run(session, teacher=TeacherKind.HUMAN)
        first, second = push_queries(session, run_id=run.id,
                                     queries=[query_spec(0), query_spec(1)])
        alice, _ = create_labeller(session, name="alice")
        held, free = [], []
        for query_id, mine in ((first, held), (second, free)):
            assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
            label, _ = submit_label(session, query_id=query_id, labeller_id=alice.id,
                                    choice="left", left_is_first=True)
            mine.append(label.id)
    taken: dict[str, list[int]] = {}

    def consume() -> None:
        with sessions() as session:
            taken["ids"] = [label.id for label in consume_labels(session, run_id=run.id)]

    # An undo half done: the first label's row locked, the run's not yet.
    with engine.connect() as undo, undo.begin():
        undo.execute(text("SELECT id FROM labels WHERE id = :id FOR UPDATE"), {"id": held[0]})
        thread = threading.Thread(target=consume)
        thread.start()
        thread.join(timeout=5)
        assert not thread.is_alive(), "the take waited for the label the undo holds"
        assert taken["ids"] == free
        undo.execute(text("SET LOCAL lock_timeout = '3s'"))
        undo.execute(select(Run.id).where(Run.id == run.id).with_for_update())  # free at once
    thread.join(timeout=30)
    with sessions() as session:  # the undo gave up: the next take has the label
        assert [label.id for label in consume_labels(session, run_id=run.id)] == held


def test_an_undo_locks_the_queries_before_the_run_as_a_submit_does(
    url: str, engine: Engine, sessions: sessionmaker[Session]
) -> None:
    """A submit locks its query's row, then the run's. An undo of the same labeller releases
    the labeller's other leases (their rows) before it locks the run, so the two never hold
    what the other waits for (PostgreSQL would abort one as a deadlock)."""
    if not url.startswith("postgresql"):
        pytest.skip("SQLite's writers take turns: no row locks to order")
    with sessions() as session:
        run = running_run(session, teacher=TeacherKind.HUMAN)
        first, second = push_queries(session, run_id=run.id,
                                     queries=[query_spec(0), query_spec(1)])
        alice, _ = create_labeller(session, name="alice")
        assert lease_next_query(session, labeller_id=alice.id, run_id=run.id) is not None
        submit_label(session, query_id=first, labeller_id=alice.id, choice="left",
                     left_is_first=True)
        leased = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
        assert leased is not None and leased.id == second
    taken: dict[str, object] = {}

    def undo() -> None:
        with sessions() as session:
            taken["back"] = withdraw_label(session, query_id=first, labeller_id=alice.id)

    # A submit of `second` half done: its query's row locked, the run's not yet.
    with engine.connect() as submit, submit.begin():
        submit.execute(select(Query.id).where(Query.id == second).with_for_update())
        thread = threading.Thread(target=undo)
        thread.start()
        time.sleep(0.5)  # the undo now waits for `second`'s row
        submit.execute(text("SET LOCAL lock_timeout = '3s'"))
        # Free at once: the undo has not locked the run while it waits.
        submit.execute(select(Run.id).where(Run.id == run.id).with_for_update())
    thread.join(timeout=30)
    assert "back" in taken
    assert read_run(sessions(), run_id=run.id).labels_used == 0


def test_an_answer_cannot_be_taken_back_once_its_round_has_closed(session: Session) -> None:
    """The worker closes a round in three steps (cancel its open queries, take the labels, read
    the round's); an undo between the first two would lease a pair of the closed round again,
    and its new answer would be charged and never trained on."""
    run = running_run(session, teacher=TeacherKind.HUMAN)
    ids = push_queries(session, run_id=run.id, queries=[query_spec(0), query_spec(1)])
    alice, _ = create_labeller(session, name="alice")
    query = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
    assert query is not None
    label, _ = submit_label(session, query_id=query.id, labeller_id=alice.id, choice="left",
                            left_is_first=True)
    cancel_queries(session, run_id=run.id, query_ids=ids)
    with pytest.raises(UndoRefused, match="round has closed"):
        withdraw_label(session, query_id=query.id, labeller_id=alice.id)
    consume_labels(session, run_id=run.id)
    assert [kept.id for kept in labels_for_queries(session, query_ids=ids)] == [label.id]
    assert read_run(session, run_id=run.id).labels_used == 1


def test_a_check_or_practice_answer_taken_back_after_its_round_closed_says_the_round_closed(
    session: Session,
) -> None:
    """The trainer never takes a check or practice answer; the round's close seals it (the
    worker's `consume_labels`), and the refusal says that, not that the trainer took it."""
    create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=100,
               teacher=TeacherKind.HUMAN,
               config={"feedback.practice_pairs": 1, "feedback.gold_rate": 0.5})
    run = claim_run(session, worker_id="worker-a")
    assert run is not None
    practice, plain, gold = push_queries(session, run_id=run.id, queries=[
        query_spec(0, gold=True), query_spec(1), query_spec(2, gold=True)])
    alice, _ = create_labeller(session, name="alice")
    for expected in (practice, plain, gold):  # a check is due after one ordinary answer
        query = lease_next_query(session, labeller_id=alice.id, run_id=run.id)
        assert query is not None and query.id == expected
        submit_label(session, query_id=query.id, labeller_id=alice.id, choice="left",
                     left_is_first=True)
    cancel_queries(session, run_id=run.id, query_ids=[plain])  # the worker closes the round
    consume_labels(session, run_id=run.id)
    for query_id in (practice, gold):
        with pytest.raises(UndoRefused, match="round .*closed") as refused:
            withdraw_label(session, query_id=query_id, labeller_id=alice.id)
        assert "trainer" not in str(refused.value)

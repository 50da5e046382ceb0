"""The practice round, on each database: a run's `feedback.practice_pairs` pairs, reserved from
its first gold pairs, come first for every newcomer at once; a practice answer is stored as
practice, never spends the budget, never counts toward a target, never pauses anyone nor counts
in gold accuracy or the gold share; taking one back leaves it practice; a practice pair is never
served as a check pair; a labeller who started on real pairs gets no practice later; the export
marks them."""

from __future__ import annotations

from queue_helpers import query_spec
from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import (
    Query,
    Run,
    claim_run,
    create_labeller,
    create_run,
    export_rows,
    lease_next_query,
    push_queries,
    submit_label,
    withdraw_label,
)
from labelqueue.gold import gold_record
from labelqueue.practice import PracticeStep, explain, practice_answered, practice_step
from labelqueue.transaction import driver_transaction


def run_with(session: Session, budget: int = 100, **config: object) -> int:
    run = create_run(session, name="p", task="dmc:cheetah_run", algo="pebble", budget=budget,
                     teacher="human", config={f"feedback.{k}": v for k, v in config.items()})
    claimed = claim_run(session, worker_id="w")
    assert claimed is not None and claimed.id == run.id
    return run.id


def gold(i: int, round: int = 0) -> dict[str, object]:
    return query_spec(100 + i, round=round, gold=True, first_segment_return=10.0,
                      second_segment_return=2.0)


def practice_ids(session: Session, run_id: int) -> list[int]:
    ids = list(session.scalars(select(Query.id).where(Query.run_id == run_id,
                                                      Query.practice.is_(True))
                               .order_by(Query.id)))
    session.commit()
    return ids


def labels_used(session: Session, run_id: int) -> int:
    used = session.scalar(select(Run.labels_used).where(Run.id == run_id))
    session.commit()
    return int(used or 0)


def answer(session: Session, labeller_id: int, run_id: int, click: str = "left") -> int:
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
    assert query is not None
    submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=click,
                 left_is_first=True)
    return query.id


def test_practice_pairs_come_first_and_are_not_measured(session: Session) -> None:
    # A threshold that would pause anyone after one wrong gold answer, practice aside.
    run_id = run_with(session, practice_pairs=2, gold_min_accuracy=1.0, gold_min_answers=1)
    regular = push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(3)])
    golds = push_queries(session, run_id=run_id, queries=[gold(i) for i in range(3)])
    assert practice_ids(session, run_id) == golds[:2]  # the first gold pairs, reserved
    ann, _ = create_labeller(session, name="ann")

    served = []
    for click in ("right", "left", "left"):  # the first practice answer is wrong (second)
        query = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
        assert query is not None
        served.append(query.id)
        label, _ = submit_label(session, query_id=query.id, labeller_id=ann.id, choice=click,
                                left_is_first=True)
        assert label.practice is (query.id in golds[:2])
    assert served[:2] == golds[:2] and served[2] == regular[0]  # practice first, then real
    assert practice_answered(session, labeller_id=ann.id, run_id=run_id) == 2
    assert practice_step(session, run_id=run_id, query_id=golds[1]) == PracticeStep(2, 2)
    with driver_transaction(session) as connection:
        assert gold_record(connection, labeller_id=ann.id, run_id=run_id) == (0, 0)
    # Not paused, although a practice answer was wrong: the next lease still serves her.
    assert lease_next_query(session, labeller_id=ann.id, run_id=run_id) is not None
    assert labels_used(session, run_id) == 1  # the one real answer, nothing for practice

    rows = [r for r in export_rows(session, run_id=run_id) if r["labeller_name"] == "ann"]
    assert [r["practice"] for r in rows] == [True, True, False]


def test_every_newcomer_practises_at_once_and_practice_never_spends(session: Session) -> None:
    run_id = run_with(session, budget=20, practice_pairs=2)
    push_queries(session, run_id=run_id, queries=[gold(0), gold(1), query_spec(0)])
    first = practice_ids(session, run_id)[0]
    people = [create_labeller(session, name=f"p{i}")[0].id for i in range(5)]
    # Five newcomers at once: each is shown the first practice pair, none waits for another.
    shown = [lease_next_query(session, labeller_id=p, run_id=run_id) for p in people]
    assert [q.id if q else None for q in shown] == [first] * 5
    # Answering and taking back a practice answer, again and again, costs nothing, and the
    # pair stays practice: answered again, it is practice again, never a check.
    for _ in range(25):
        label, _ = submit_label(session, query_id=first, labeller_id=people[0], choice="right",
                                left_is_first=True)
        assert label.practice
        withdrawn = withdraw_label(session, query_id=first, labeller_id=people[0])
        assert withdrawn.query.practice and withdrawn.query.lease_holder == people[0]
    assert labels_used(session, run_id) == 0
    with driver_transaction(session) as connection:
        assert gold_record(connection, labeller_id=people[0], run_id=run_id) == (0, 0)


def test_a_practice_pair_is_never_a_check_pair(session: Session) -> None:
    # Half the answers due a check pair: only the gold pairs after the practice may be one.
    run_id = run_with(session, practice_pairs=2, gold_rate=0.5)
    ids = push_queries(session, run_id=run_id, queries=[
        gold(0), gold(1), query_spec(0), gold(2), query_spec(1), gold(3), query_spec(2)])
    practice = practice_ids(session, run_id)
    ann, _ = create_labeller(session, name="ann")
    served = [answer(session, ann.id, run_id) for _ in range(7)
              if lease_next_query(session, labeller_id=ann.id, run_id=run_id) is not None]
    assert served[:2] == practice
    assert {ids[3], ids[5]} & set(served[2:])  # checks were served, but never a practice pair
    assert not set(served[2:]) & set(practice)


def test_no_practice_for_who_started_on_real_pairs(session: Session) -> None:
    run_id = run_with(session, practice_pairs=2)
    [first] = push_queries(session, run_id=run_id, queries=[query_spec(0)])
    bob, _ = create_labeller(session, name="bob")
    query = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert query is not None and query.id == first  # no practice pair yet: real pairs
    submit_label(session, query_id=first, labeller_id=bob.id, choice="left", left_is_first=True)
    push_queries(session, run_id=run_id, queries=[gold(0), query_spec(1)])
    query = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert query is not None and not query.gold  # no practice for him now, and no gold rate
    assert practice_answered(session, labeller_id=bob.id, run_id=run_id) == 0


def test_practice_pairs_are_reserved_once_from_the_first_gold_pairs(session: Session) -> None:
    run_id = run_with(session, practice_pairs=3)
    push_queries(session, run_id=run_id, queries=[query_spec(0), gold(0), gold(1)])
    assert len(practice_ids(session, run_id)) == 2
    later = push_queries(session, run_id=run_id,
                         queries=[gold(0, round=1), gold(1, round=1), query_spec(0, round=1)])
    assert practice_ids(session, run_id)[-1] == later[0]  # the third, then no more
    assert len(practice_ids(session, run_id)) == 3


def test_the_explanation_is_a_ratio_never_the_returns() -> None:
    assert explain(left_return=30.0, right_return=10.0) == (
        "left", "The left clip is better: by the task's reward it did 3.0× as well as the "
        "right one.")
    side, text = explain(left_return=0.0, right_return=4.06)
    assert side == "right" and "earned none" in text and "4.06" not in text
    assert explain(left_return=-5.0, right_return=2.0)[1].endswith("the left one lost some.")
    assert explain(left_return=-1.0, right_return=-3.0)[0] == "left"
    assert explain(left_return=1.0, right_return=1.0)[0] == "equal"

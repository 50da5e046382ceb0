"""The practice round, on each database: a run's `feedback.practice_pairs` gold pairs come
first, are stored as practice, never pause anyone nor count in gold accuracy or the gold share;
a labeller who started on real pairs gets no practice later; the export marks them."""

from __future__ import annotations

from queue_helpers import query_spec
from sqlalchemy.orm import Session

from labelqueue import (
    claim_run,
    create_labeller,
    create_run,
    export_rows,
    lease_next_query,
    push_queries,
    submit_label,
)
from labelqueue.gold import gold_record
from labelqueue.practice import explain, practice_progress
from labelqueue.transaction import driver_transaction


def run_with(session: Session, **config: object) -> int:
    run = create_run(session, name="p", task="dmc:cheetah_run", algo="pebble", budget=100,
                     teacher="human", config={f"feedback.{k}": v for k, v in config.items()})
    claimed = claim_run(session, worker_id="w")
    assert claimed is not None and claimed.id == run.id
    return run.id


def gold(i: int) -> dict[str, object]:
    return query_spec(100 + i, gold=True, first_segment_return=10.0, second_segment_return=2.0)


def test_practice_pairs_come_first_and_are_not_measured(session: Session) -> None:
    # A threshold that would pause anyone after one wrong gold answer, practice aside.
    run_id = run_with(session, practice_pairs=2, gold_min_accuracy=1.0, gold_min_answers=1)
    regular = push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(3)])
    golds = push_queries(session, run_id=run_id, queries=[gold(i) for i in range(3)])
    ann, _ = create_labeller(session, name="ann")

    served = []
    for click in ("right", "left", "left"):  # the first practice answer is wrong (second)
        query = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
        assert query is not None
        served.append(query.id)
        label, _ = submit_label(session, query_id=query.id, labeller_id=ann.id, choice=click,
                                left_is_first=True)
        assert label.practice is (query.id in golds)
    assert served[:2] == golds[:2] and served[2] == regular[0]  # practice first, then real
    done, pairs, step = practice_progress(session, labeller_id=ann.id, run_id=run_id)
    assert (done, pairs, step) == (2, 2, None)
    with driver_transaction(session) as connection:
        assert gold_record(connection, labeller_id=ann.id, run_id=run_id) == (0, 0)
    # Not paused, although a practice answer was wrong: the next lease still serves her.
    assert lease_next_query(session, labeller_id=ann.id, run_id=run_id) is not None

    rows = [r for r in export_rows(session, run_id=run_id) if r["labeller_name"] == "ann"]
    assert [r["practice"] for r in rows] == [True, True, False]


def test_no_practice_for_who_started_on_real_pairs(session: Session) -> None:
    run_id = run_with(session, practice_pairs=2)
    [first] = push_queries(session, run_id=run_id, queries=[query_spec(0)])
    bob, _ = create_labeller(session, name="bob")
    query = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert query is not None and query.id == first  # no gold pair open yet: real pairs
    submit_label(session, query_id=first, labeller_id=bob.id, choice="left", left_is_first=True)
    push_queries(session, run_id=run_id, queries=[gold(0), query_spec(1)])
    query = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert query is not None and not query.gold  # the gold rate is 0: no gold, no practice
    assert practice_progress(session, labeller_id=bob.id, run_id=run_id)[2] is None


def test_the_explanation_is_a_ratio_never_the_returns() -> None:
    assert explain(left_return=30.0, right_return=10.0) == (
        "left", "The left clip is better: by the task's reward it did 3.0× as well as the "
        "right one.")
    side, text = explain(left_return=0.0, right_return=4.06)
    assert side == "right" and "earned none" in text and "4.06" not in text
    assert explain(left_return=-5.0, right_return=2.0)[1].endswith("the left one lost some.")
    assert explain(left_return=-1.0, right_return=-3.0)[0] == "left"
    assert explain(left_return=1.0, right_return=1.0)[0] == "equal"

"""The budget counts answers everywhere: with k answers per query a round asks for no more
queries than the budget can pay k answers for, the queue's count, the dashboard's and the run's
rounds.csv agree, and the run asks for nothing once the budget is spent."""

from __future__ import annotations

import csv
import threading
import time
from collections import Counter

from sqlalchemy import select
from worker_helpers import (
    RUN,
    SCREEN,
    database,
    labels_jsonl,
    run_row,
    settle_labels,
    shadow_choices,
    start_worker,
    worker_config,
)

from labelqueue import (
    Label,
    MetricStream,
    Query,
    RunStatus,
    create_labeller,
    create_run,
    lease_next_query,
    read_metrics,
    submit_label,
)

K, BUDGET, PEOPLE = 3, 40, 7


def test_k_answers_per_query_from_many_people_never_overspend_the_budget(tmp_path):
    url, sessions = database(tmp_path)
    config = RUN["config"] | {"feedback.labels_per_query": K}
    with sessions() as session:
        run = create_run(session, name="crowd", teacher="human",
                         **RUN | {"budget": BUDGET, "config": config})
        people = [create_labeller(session, name=f"p{i}")[0].id for i in range(PEOPLE)]
    worker = start_worker(worker_config(url, tmp_path / "data"))
    stop = threading.Event()

    def label(person: int) -> None:
        with sessions() as session:
            while not stop.is_set():
                query = lease_next_query(session, labeller_id=person, run_id=run.id)
                if query is None:
                    time.sleep(0.05)
                    continue
                choice = SCREEN[shadow_choices(sessions, run.id)[query.id]]
                submit_label(session, query_id=query.id, labeller_id=person, choice=choice,
                             left_is_first=True)
                settle_labels(sessions, run.id)  # past the undo window: usable at once

    crowd = [threading.Thread(target=label, args=(p,), daemon=True) for p in people]
    for thread in crowd:
        thread.start()
    try:
        worker.join(timeout=300)
        assert not worker.is_alive()
    finally:
        stop.set()
        for thread in crowd:
            thread.join(timeout=30)

    done = run_row(sessions, run.id)
    assert done.status is RunStatus.FINISHED
    with sessions() as session:
        labels = session.scalars(select(Label).where(Label.run_id == run.id)).all()
        queries = session.scalars(select(Query).where(Query.run_id == run.id)).all()
        rounds = read_metrics(session, run_id=run.id, stream=MetricStream.ROUNDS)
    # Round 0: 10 queries (30 answers); round 1: what 10 answers left pay for, 3 queries.
    assert [r.values["queries"] for r in rounds] == [10, 3]
    assert [r.values["answers"] for r in rounds] == [30, 9]
    per_query = Counter(label.query_id for label in labels)
    assert sorted(per_query.values()) == [K] * 13 and len(queries) == 13
    assert all(len({lab.labeller_id for lab in labels if lab.query_id == q}) == K
               for q in per_query)  # k different people each
    # One count everywhere: the queue's (the dashboard's "labels / budget"), the curves' and
    # rounds.csv's, the stored labels; within the budget.
    assert done.labels_used == len(labels) == 39 <= BUDGET
    assert rounds[-1].values["labels_used"] == 39
    run_dir = tmp_path / "data" / "runs" / f"run-{run.id}"
    with open(run_dir / "rounds.csv", newline="") as f:
        assert [int(float(row["labels_used"])) for row in csv.DictReader(f)] == [30, 39]
    assert len(labels_jsonl(run_dir)) == 13  # one trained answer per query
    assert done.progress["labels_used"] == 39

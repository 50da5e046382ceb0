"""Real races: threads with sessions of their own hit the same rows at the same moment.

On SQLite every thread has its own connection, so they contend for the database's write lock
exactly as separate server and worker processes would.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from itertools import combinations
from typing import TypeVar

import pytest
from queue_helpers import query_spec, running_run
from sqlalchemy import Connection, Engine, func, select, text, update
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    Label,
    Query,
    QueryStatus,
    Run,
    TeacherKind,
    claim_run,
    consume_labels,
    create_labeller,
    create_run,
    lease_next_query,
    paused_labellers,
    push_queries,
    submit_label,
)
from labelqueue.models import utcnow

T = TypeVar("T")


def race(sessions: sessionmaker[Session], n: int, act: Callable[[Session, int], T]) -> list[T]:
    """Run act(session, i) in n threads released together; their results, by i."""
    start = threading.Barrier(n)

    def one(i: int) -> T:
        with sessions() as session:
            start.wait(timeout=30)
            return act(session, i)

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(one, range(n), timeout=60))


def test_racing_leases_never_share_a_query(sessions: sessionmaker[Session]) -> None:
    with sessions() as session:
        run = running_run(session)
        ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(5)])
        labellers = [create_labeller(session, name=f"l{i}")[0].id for i in range(8)]

    leased = race(
        sessions,
        8,
        lambda s, i: lease_next_query(s, labeller_id=labellers[i], run_id=run.id),
    )

    got = [(labellers[i], q.id) for i, q in enumerate(leased) if q is not None]
    assert sorted(query_id for _, query_id in got) == ids  # each query to exactly one labeller
    assert leased.count(None) == 3  # more labellers than queries: the extras get nothing
    with sessions() as session:
        holders = dict(session.execute(select(Query.id, Query.lease_holder)).tuples().all())
    assert holders == {query_id: labeller for labeller, query_id in got}


def test_labellers_racing_through_a_queue_each_see_a_query_once(
    sessions: sessionmaker[Session],
) -> None:
    with sessions() as session:
        run = running_run(session)
        specs = [query_spec(i, needs_labels=3) for i in range(6)]
        ids = push_queries(session, run_id=run.id, queries=specs)
        labellers = [create_labeller(session, name=f"l{i}")[0].id for i in range(6)]

    def still_to_answer(session: Session, labeller: int) -> int:
        mine = select(Label.id).where(Label.query_id == Query.id, Label.labeller_id == labeller)
        count = session.scalar(
            select(func.count())
            .select_from(Query)
            .where(Query.status != QueryStatus.LABELLED, ~mine.exists())
        )
        session.commit()
        return count or 0

    def label_until_done(session: Session, i: int) -> list[int]:
        seen: list[int] = []
        while True:
            query = lease_next_query(session, labeller_id=labellers[i], run_id=run.id)
            if query is None:
                # Nothing free now; what is left may be leased to others and come back.
                if not still_to_answer(session, labellers[i]):
                    return seen
                time.sleep(0.002)
                continue
            seen.append(query.id)
            _, created = submit_label(
                session,
                query_id=query.id,
                labeller_id=labellers[i],
                choice="left",
                left_is_first=i % 2 == 0,
            )
            assert created

    seen = race(sessions, 6, label_until_done)

    for queries in seen:
        assert len(queries) == len(set(queries))  # never the same query twice
    assert Counter(q for queries in seen for q in queries) == {query_id: 3 for query_id in ids}
    with sessions() as session:
        assert session.scalar(select(func.count()).select_from(Label)) == 18
        assert session.get(Run, run.id).labels_used == 18  # type: ignore[union-attr]
        statuses = set(session.scalars(select(Query.status)))
        assert statuses == {QueryStatus.LABELLED}


def test_racing_submits_of_one_answer_store_one_row(sessions: sessionmaker[Session]) -> None:
    with sessions() as session:
        run = running_run(session)
        [query_id] = push_queries(session, run_id=run.id, queries=[query_spec(0)])
        alice = create_labeller(session, name="alice")[0].id
        lease_next_query(session, labeller_id=alice, run_id=run.id)

    results = race(
        sessions,
        8,
        lambda s, i: submit_label(
            s, query_id=query_id, labeller_id=alice, choice="right", left_is_first=True
        ),
    )

    assert sum(created for _, created in results) == 1
    assert len({label.id for label, _ in results}) == 1
    with sessions() as session:
        assert session.scalar(select(func.count()).select_from(Label)) == 1
        assert session.get(Run, run.id).labels_used == 1  # type: ignore[union-attr]


def test_racing_workers_claim_each_run_once(sessions: sessionmaker[Session]) -> None:
    with sessions() as session:
        runs = [
            create_run(session, name=f"r{i}", task="dmc:cheetah_run", algo="pebble", budget=10).id
            for i in range(2)
        ]

    claimed = race(sessions, 8, lambda s, i: claim_run(s, worker_id=f"w{i}"))
    winners = {run.id: run.worker_id for run in claimed if run is not None}
    assert sorted(winners) == runs and claimed.count(None) == 6

    # Both workers die; the survivors race for the orphaned runs.
    with sessions() as session:
        session.execute(update(Run).values(heartbeat_at=utcnow().replace(year=2000)))
        session.commit()
    claimed = race(sessions, 8, lambda s, i: claim_run(s, worker_id=f"v{i}", stale_after=60))
    takers = [run for run in claimed if run is not None]
    assert sorted(run.id for run in takers) == runs
    with sessions() as session:
        owners = dict(session.execute(select(Run.id, Run.worker_id)).tuples().all())
    assert owners == {run.id: run.worker_id for run in takers}


def test_racing_consumers_split_the_labels_between_them(sessions: sessionmaker[Session]) -> None:
    with sessions() as session:
        run = running_run(session)
        ids = push_queries(session, run_id=run.id, queries=[query_spec(i) for i in range(24)])
        teacher = create_labeller(session, name="teacher")[0].id
    done = threading.Event()

    def act(session: Session, i: int) -> list[int]:
        if i == 0:  # the teacher answers while three consumers poll
            for query_id in ids:
                lease_next_query(session, labeller_id=teacher, run_id=run.id)
                submit_label(
                    session,
                    query_id=query_id,
                    labeller_id=teacher,
                    choice="left",
                    left_is_first=True,
                )
            done.set()
            return []
        taken: list[int] = []
        while True:
            finished = done.is_set()
            taken += [label.id for label in consume_labels(session, run_id=run.id)]
            if finished:
                return taken

    results = race(sessions, 4, act)[1:]

    with sessions() as session:
        every_label = set(session.scalars(select(Label.id)))
    assert len(every_label) == 24
    assert set().union(*map(set, results)) == every_label
    for a, b in combinations(results, 2):
        assert not set(a) & set(b)
    assert sum(map(len, results)) == 24


def lock_waits(connection: Connection, n: int) -> bool:
    """Whether `n` sessions of this database wait for a lock, within 5 s."""
    for _ in range(100):
        connection.execute(text("SELECT pg_stat_clear_snapshot()"))  # else read once per xact
        if connection.scalar(text("SELECT count(*) FROM pg_stat_activity WHERE wait_event_type "
                                  "= 'Lock' AND datname = current_database()")) == n:
            return True
        time.sleep(0.05)
    return False


def test_two_gold_answers_at_once_that_both_pause_make_one_pause(
    url: str, engine: Engine, sessions: sessionmaker[Session]
) -> None:
    """Two tabs of one labeller send a wrong check answer each at the same moment, each enough
    to pause them. A gold answer locks its run's row before it reads the gold record, so the
    second sees the first one's pause: both answers stored and one pause, where a second insert
    of the pause would break its unique constraint (a 500 over REST)."""
    if not url.startswith("postgresql"):
        pytest.skip("SQLite's writers take turns: no row locks to order")
    with sessions() as session:
        create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=10,
                   teacher=TeacherKind.HUMAN, config={"feedback.gold_min_accuracy": 0.5,
                                                      "feedback.gold_min_answers": 1})
        run = claim_run(session, worker_id="w")
        assert run is not None
        golds = push_queries(session, run_id=run.id,
                             queries=[query_spec(i, gold=True) for i in range(2)])
        alice = create_labeller(session, name="alice")[0].id
        session.execute(update(Query).where(Query.id.in_(golds)).values(  # one on each tab
            status=QueryStatus.LEASED, lease_holder=alice, leased_at=utcnow(),
            lease_expires_at=utcnow() + timedelta(minutes=2)))
        session.commit()

    def wrong(query_id: int) -> tuple[Label, bool]:  # the first segment: the worse one
        with sessions() as session:
            return submit_label(session, query_id=query_id, labeller_id=alice, choice="left",
                                left_is_first=True)

    with ThreadPoolExecutor(max_workers=2) as pool:
        with engine.connect() as holder, holder.begin():
            holder.execute(select(Run.id).where(Run.id == run.id).with_for_update())
            answers = [pool.submit(wrong, query_id) for query_id in golds]
            assert lock_waits(holder, 2), "the answers did not both wait for the run's row"
        results = [answer.result(timeout=30) for answer in answers]
    assert [created for _, created in results] == [True, True]
    with sessions() as session:
        [pause] = paused_labellers(session, run_id=run.id)
    assert (pause.labeller_id, pause.gold_answers, pause.gold_correct) == (alice, 1, 0)

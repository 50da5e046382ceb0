"""The run page's label throughput (`GET /api/runs/{id}/throughput`) on a run with many labels.

A fresh queue database (SQLite in a temporary folder, or with --database postgres a new database
in the cluster of `scripts/with_postgres.sh`) gets one run with --labels labels answered over
--hours hours: 75 % human with an answer time of 2-20 s, 25 % scripted, 1 % of them
taken back (withdrawn), and all others but the last minute's taken by the trainer. Three ways
of answering the endpoint are timed in this process, alternating, --repeats times each, with
the CPU time of the process (SQLite's work included):

- "Python": every label of the run read and bucketed in Python (how the endpoint worked before),
  withdrawn labels left out, the median of the latest 1000 human answer times;
- "SQL": the counts per bucket and source and the median answer time worked out in SQL
  (`runviews.label_stats.label_throughput`), what a poll costs after a new label;
- "SQL, unchanged": the endpoint's function when no label came or went since the last poll
  (the run, and the labels' fingerprint, read; the answer kept from the last poll).

The Python and SQL answers are compared first; the script exits 1 if they differ.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_throughput.py
    PYTHONPATH=. .venv/bin/python benchmarks/bench_throughput.py --labels 100000
    bash scripts/with_postgres.sh env PYTHONPATH=. .venv/bin/python \
        benchmarks/bench_throughput.py --database postgres
"""

from __future__ import annotations

import argparse
import math
import os
import random
import statistics
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

from bench_label_api import fresh_database, query_spec
from sqlalchemy import insert, select
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    LabelSource,
    Query,
    Run,
    create_labeller,
    make_engine,
    session_factory,
)
from runviews.label_stats import MEDIAN_OF, label_throughput
from server import services
from server.routes import stats
from server.schemas import Throughput, ThroughputBucket


def python_throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
    """Every standing label of the run read, then counted in Python (the endpoint before)."""
    services.get_run(session, run_id=run_id)
    with services.reading(session):
        rows = session.execute(
            select(Label.source, Label.shown_at, Label.answered_at)
            .where(Label.run_id == run_id, Label.withdrawn_at.is_(None)).order_by(Label.id)
        ).all()

    def bucket(when: datetime) -> datetime:
        return datetime.fromtimestamp(math.floor(when.timestamp() / bucket_s) * bucket_s, UTC)

    per_bucket = Counter(bucket(answered) for _, _, answered in rows)
    by_source = Counter(LabelSource(source).value for source, _, _ in rows)
    answer_s = [(answered - shown).total_seconds() for source, shown, answered in rows
                if source == LabelSource.HUMAN and shown is not None][-MEDIAN_OF:]
    return Throughput(
        run_id=run_id, bucket_s=bucket_s, total=len(rows),
        by_source={source.value: by_source[source.value] for source in LabelSource},
        median_answer_s=statistics.median(answer_s) if answer_s else None,
        buckets=[ThroughputBucket(t=t, labels=n) for t, n in sorted(per_bucket.items())],
    )


def sql_throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
    """The SQL computation on every call (a poll after a new label)."""
    counted = label_throughput(session, run_id=run_id, bucket_s=bucket_s)
    return Throughput(run_id=run_id, bucket_s=bucket_s, total=counted.total,
                      by_source=counted.by_source, median_answer_s=counted.median_answer_s,
                      buckets=[ThroughputBucket(t=t, labels=n) for t, n in counted.buckets])


def seed(url: str, n: int, hours: float, rng: random.Random) -> int:
    engine = make_engine(url)
    with Session(engine) as session:
        labeller, _ = create_labeller(session, name="alice")
        labeller_id = labeller.id
    end = datetime.now(UTC).replace(microsecond=0)
    start = end - timedelta(hours=hours)
    with engine.begin() as connection:
        run_id = connection.execute(insert(Run).values(
            name="busy", task="dmc:cheetah_run", algo="sepoa", preset="small", seed=1,
            config={}, teacher="human", teacher_params={}, budget=n, labels_used=n, step=0,
            progress={}, status="running", created_at=start)).inserted_primary_key[0]
    for first in range(0, n, 10_000):
        positions = range(first, min(n, first + 10_000))
        with engine.begin() as connection:
            ids = connection.execute(
                insert(Query).returning(Query.id, sort_by_parameter_order=True),
                [query_spec(position // 100, position) | {
                    "run_id": run_id, "needs_labels": 1, "label_count": 1,
                    "status": "labelled", "created_at": start} for position in positions],
            ).scalars().all()
            labels = []
            for position, query_id in zip(positions, ids, strict=True):
                answered = start + timedelta(seconds=hours * 3600 * position / n
                                             + rng.random())
                source = rng.choices(("human", "scripted"), (75, 25))[0]
                shown = answered - timedelta(seconds=rng.uniform(2, 20) if source == "human"
                                             else rng.uniform(0, 0.5))
                withdrawn = answered + timedelta(seconds=3) if rng.random() < 0.01 else None
                labels.append({
                    "query_id": query_id, "run_id": run_id, "labeller_id": labeller_id,
                    "choice": "left", "left_is_first": True, "answer": "first",
                    "source": source, "shown_at": shown, "answered_at": answered,
                    "withdrawn_at": withdrawn,
                    # The trainer has taken every standing label but the last minute's.
                    "consumed_at": answered + timedelta(seconds=20)
                    if withdrawn is None and answered < end - timedelta(minutes=1) else None,
                })
            connection.execute(insert(Label), labels)
    engine.dispose()
    return int(run_id)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=int, default=20_000, help="labels of the run")
    parser.add_argument("--hours", type=float, default=6.0, help="over how long they came")
    parser.add_argument("--bucket-s", type=int, default=300,
                        help="bucket length (run.js asks for 300 s on a run 2-10 h old)")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls of each side")
    parser.add_argument("--database", choices=("sqlite", "postgres"), default="sqlite")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp, fresh_database(args, Path(tmp)) as url:
        run_id = seed(url, args.labels, args.hours, random.Random(0))
        engine = make_engine(url)
        sessions = session_factory(engine)
        sides: dict[str, Callable[..., Throughput]] = {
            "Python (every label read)": python_throughput,
            "SQL": sql_throughput,
            "SQL, unchanged since last poll": stats.run_throughput,
        }
        with sessions() as session:
            answers = {name: side(session, run_id=run_id, bucket_s=args.bucket_s)
                       for name, side in sides.items()}
        reference = answers["Python (every label read)"].model_dump()
        for name, answer in answers.items():
            got = answer.model_dump()
            # SQL works the answer times out in floating point: the same to the microsecond.
            if math.isclose(got["median_answer_s"], reference["median_answer_s"], abs_tol=1e-6):
                got["median_answer_s"] = reference["median_answer_s"]
            if got != reference:
                print(f"{name} answers differently from Python:\n{answer}\n{reference}")
                sys.exit(1)
        cpu: dict[str, list[float]] = {name: [] for name in sides}
        wall: dict[str, list[float]] = {name: [] for name in sides}
        for _ in range(args.repeats):
            for name, side in sides.items():
                with sessions() as session:
                    c0, w0 = time.process_time(), time.perf_counter()
                    side(session, run_id=run_id, bucket_s=args.bucket_s)
                    cpu[name].append(time.process_time() - c0)
                    wall[name].append(time.perf_counter() - w0)
        engine.dispose()

    standing = reference["total"]
    print(f"throughput of a run with {args.labels} labels ({standing} standing) over "
          f"{args.hours:g} h, {args.bucket_s} s buckets ({len(reference['buckets'])}), "
          f"{args.database}; median of {args.repeats} calls each, alternating; "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}")
    print(f"{'side':34s} {'CPU ms':>8s} {'wall ms':>8s} {'vs Python (CPU)':>16s}")
    base = statistics.median(cpu["Python (every label read)"])
    for name in sides:
        c, w = statistics.median(cpu[name]), statistics.median(wall[name])
        print(f"{name:34s} {c * 1e3:8.2f} {w * 1e3:8.2f} {c / base:15.2f}x")
    print("answers identical: yes")


if __name__ == "__main__":
    main()

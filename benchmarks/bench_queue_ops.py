"""The label API's queue work per round trip, in process: CPU time, against the labels stored.

One thread runs what the server's label thread runs for each round trip, without HTTP:
`server.services.next_query` (the token's labeller leases the oldest open query) and
`server.services.submit_answer` (the answer is stored), each in a session of its own, on a
fresh SQLite queue database. Ten labellers take turns on one human-taught run whose queries
were pushed up front. Before timing, an older finished run with `--history N` answered queries
is seeded, as a server that has been labelling for a while holds: a lease's cost must not grow
with it. Each history size is timed on a database of its own; the table gives CPU time per
round trip (median of `--repeats`).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_queue_ops.py
    PYTHONPATH=. .venv/bin/python benchmarks/bench_queue_ops.py --page --history 0
    PYTHONPATH=$OLDER_TREE .venv/bin/python benchmarks/bench_queue_ops.py --history 0 100000

PYTHONPATH names the checkout whose queue package and services are measured (run the script
from this checkout: its own folder comes first on the path, before PYTHONPATH, only for
`benchmarks/`).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_label_api import SECRET_KEY, push_warmup, seed_history  # noqa: E402

from labelqueue import create_labeller, create_run, make_engine, migrate, session_factory  # noqa: E402
from server import services  # noqa: E402
from server.schemas import LabelSubmit  # noqa: E402
from server.settings import Settings  # noqa: E402


def per_round_trip(history: int, round_trips: int, repeats: int, page: bool) -> list[float]:
    """CPU seconds per round trip, one figure per repeat, on a fresh database."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-queue-ops-"))
    url = f"sqlite:///{tmp / 'queue.db'}"
    migrate(url)
    settings = Settings(database_url=url, data_dir=str(tmp), secret_key=SECRET_KEY)
    engine = make_engine(url)
    sessions = session_factory(engine)
    with sessions() as session:
        labellers = [create_labeller(session, name=f"labeller-{i}")[0].id for i in range(10)]
        run = create_run(session, name="now", task="dmc:cheetah_run", algo="pebble",
                         budget=10**7, preset="small", teacher="human")
    if history:
        seed_history(url, labellers[0], history)
    warmup = 100
    push_warmup(url, tmp, run.id, warmup + round_trips * repeats + 10, 1)
    shown: dict[int, int] = {}  # --page: the query each labeller's page shows

    def lease(labeller_id: int, ahead_of: int | None) -> int:
        with sessions() as session:
            query = services.next_query(session, settings=settings, labeller_id=labeller_id,
                                        run_id=run.id if page else None, ahead_of=ahead_of)
        assert query is not None, "the run ran out of queries"
        return query.query_id

    def round_trip(labeller_id: int) -> None:
        if page:  # lease the next pair ahead of the one shown, then answer the one shown
            if labeller_id not in shown:
                shown[labeller_id] = lease(labeller_id, None)
            answered, shown[labeller_id] = shown[labeller_id], lease(labeller_id,
                                                                     shown[labeller_id])
        else:
            answered = lease(labeller_id, None)
        with sessions() as session:
            services.submit_answer(session, settings=settings, labeller_id=labeller_id,
                                   query_id=answered,
                                   body=LabelSubmit(choice="left", shown_at=datetime.now(UTC)))

    try:
        for i in range(warmup):
            round_trip(labellers[i % 10])
        figures = []
        for _ in range(repeats):
            start = time.process_time()
            for i in range(round_trips):
                round_trip(labellers[i % 10])
            figures.append((time.process_time() - start) / round_trips)
    finally:
        engine.dispose()
        shutil.rmtree(tmp, ignore_errors=True)
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--history", type=int, nargs="+", default=[0, 10_000, 100_000],
                        help="labels of an older run stored before timing, one database each")
    parser.add_argument("--round-trips", type=int, default=500, help="per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--page", action="store_true",
                        help="as the label page asks: next with the run's id and ahead_of the "
                        "pair shown (its preload), then the answer to the pair shown")
    args = parser.parse_args()
    if min(args.history) < 0 or args.round_trips < 1 or args.repeats < 1:
        parser.error("--history must be >= 0, --round-trips and --repeats >= 1")
    print(f"queue work per round trip (lease + submit{', as the page asks' if args.page else ''}"
          f", one thread, SQLite), "
          f"{args.round_trips} round trips x {args.repeats}; load average "
          f"{os.getloadavg()[0]:.2f}; checkout {os.environ.get('PYTHONPATH', '.')}")
    print(f"{'older labels':>13} {'CPU ms per round trip (median)':>32} {'range':>16}")
    for history in args.history:
        seconds = per_round_trip(history, args.round_trips, args.repeats, args.page)
        figures = [1000 * f for f in seconds]
        print(f"{history:>13} {statistics.median(figures):>32.3f} "
              f"{min(figures):>7.3f}-{max(figures):<8.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

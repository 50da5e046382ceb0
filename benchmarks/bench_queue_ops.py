"""The label API's queue work per round trip, in process: CPU time, against the labels stored.

One thread runs what the server's label thread runs for each round trip, without HTTP:
`server.services.next_query` (the token's labeller leases the oldest open query) and
`server.services.submit_answer` (the answer is stored), each in a session of its own, on a
fresh SQLite queue database. With `--app` the round trips go through the app itself instead:
its ASGI callable, called directly with each request (no sockets, no HTTP parsing), middleware,
routing, token check, validation and JSON included; the difference from the plain figure is
what the web framework adds to the queue work. `--calls` also counts the Python function calls
per round trip under cProfile (its timing is not used), a figure the machine's load does not
move.

Ten labellers take turns on one human-taught run whose queries were pushed up front. Before
timing, an older finished run with `--history N` answered queries is seeded, as a server that
has been labelling for a while holds: a lease's cost must not grow with it. Each history size is
timed on a database of its own; the table gives CPU time per round trip (median of `--repeats`).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_queue_ops.py
    PYTHONPATH=. .venv/bin/python benchmarks/bench_queue_ops.py --page --history 0
    PYTHONPATH=. .venv/bin/python benchmarks/bench_queue_ops.py --app --calls --history 0
    PYTHONPATH=$OLDER_TREE .venv/bin/python benchmarks/bench_queue_ops.py --history 0 100000

PYTHONPATH names the checkout whose queue package and services are measured (run the script
from this checkout: its own folder comes first on the path, before PYTHONPATH, only for
`benchmarks/`).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import json
import os
import pstats
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_label_api import SECRET_KEY, push_warmup, seed_history  # noqa: E402

from labelqueue import create_labeller, create_run, make_engine, migrate, session_factory  # noqa: E402
from server import services  # noqa: E402
from server.app import create_app  # noqa: E402
from server.schemas import LabelSubmit  # noqa: E402
from server.settings import Settings  # noqa: E402


class AppClient:
    """Requests straight to the app's ASGI callable, in this thread's event loop."""

    def __init__(self, settings: Settings):
        self.app = create_app(settings)
        self.loop = asyncio.new_event_loop()
        self.lifespan = self.app.router.lifespan_context(self.app)
        self.loop.run_until_complete(self.lifespan.__aenter__())

    def close(self) -> None:
        self.loop.run_until_complete(self.lifespan.__aexit__(None, None, None))
        self.loop.close()

    def call(self, method: str, path: str, token: str, body: bytes = b"") -> tuple[int, bytes]:
        path, _, query = path.partition("?")
        headers = [(b"host", b"bench"), (b"authorization", f"Bearer {token}".encode()),
                   (b"content-type", b"application/json"),
                   (b"content-length", str(len(body)).encode())]
        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "method": method, "scheme": "http", "path": path, "raw_path": path.encode(),
                 "query_string": query.encode(), "root_path": "", "headers": headers,
                 "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 80), "state": {}}
        messages = [{"type": "http.request", "body": body, "more_body": False}]
        answer: dict[str, Any] = {"body": b""}

        async def receive() -> dict[str, Any]:
            return messages.pop() if messages else {"type": "http.disconnect"}

        async def send(message: dict[str, Any]) -> None:
            if message["type"] == "http.response.start":
                answer["status"] = message["status"]
            else:
                answer["body"] += message.get("body", b"")

        self.loop.run_until_complete(self.app(scope, receive, send))
        return answer["status"], answer["body"]


def per_round_trip(history: int, round_trips: int, repeats: int, page: bool, app: bool,
                   calls: bool) -> tuple[list[float], float | None]:
    """CPU seconds per round trip, one figure per repeat, on a fresh database; and with
    `calls` the function calls per round trip of one more repeat, under cProfile."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-queue-ops-"))
    url = f"sqlite:///{tmp / 'queue.db'}"
    migrate(url)
    settings = Settings(database_url=url, data_dir=str(tmp), secret_key=SECRET_KEY)
    engine = make_engine(url)
    sessions = session_factory(engine)
    with sessions() as session:
        made = [create_labeller(session, name=f"labeller-{i}") for i in range(10)]
        labellers = [labeller.id for labeller, _ in made]
        tokens = {labeller.id: token for labeller, token in made}
        run = create_run(session, name="now", task="dmc:cheetah_run", algo="pebble",
                         budget=10**7, preset="small", teacher="human")
    if history:
        seed_history(url, labellers[0], history)
    warmup = 100
    push_warmup(url, tmp, run.id, warmup + round_trips * (repeats + calls) + 10, 1)
    shown: dict[int, int] = {}  # --page: the query each labeller's page shows
    client = AppClient(settings) if app else None

    def lease_in_process(labeller_id: int, ahead_of: int | None) -> int | None:
        with sessions() as session:
            query = services.next_query(session, settings=settings, labeller_id=labeller_id,
                                        run_id=run.id if page else None, ahead_of=ahead_of)
        return None if query is None else query.query_id

    def answer_in_process(labeller_id: int, query_id: int) -> None:
        with sessions() as session:
            services.submit_answer(session, settings=settings, labeller_id=labeller_id,
                                   query_id=query_id,
                                   body=LabelSubmit(choice="left", shown_at=datetime.now(UTC)))

    def lease_through_app(labeller_id: int, ahead_of: int | None) -> int | None:
        assert client is not None
        asked = {"run_id": run.id if page else None, "ahead_of": ahead_of}
        query = "&".join(f"{k}={v}" for k, v in asked.items() if v is not None)
        status, body = client.call("GET", f"/api/label/next?{query}", tokens[labeller_id])
        assert status in (200, 204), (status, body)
        return json.loads(body)["query_id"] if status == 200 else None

    def answer_through_app(labeller_id: int, query_id: int) -> None:
        assert client is not None
        body = json.dumps({"choice": "left", "shown_at": datetime.now(UTC).isoformat()})
        status, answer = client.call("POST", f"/api/label/{query_id}", tokens[labeller_id],
                                     body.encode())
        assert status == 201, (status, answer)

    lease_of: Callable[[int, int | None], int | None] = (
        lease_through_app if app else lease_in_process
    )
    answer = answer_through_app if app else answer_in_process

    def lease(labeller_id: int, ahead_of: int | None) -> int:
        query_id = lease_of(labeller_id, ahead_of)
        assert query_id is not None, "the run ran out of queries"
        return query_id

    def round_trip(labeller_id: int) -> None:
        if page:  # lease the next pair ahead of the one shown, then answer the one shown
            if labeller_id not in shown:
                shown[labeller_id] = lease(labeller_id, None)
            answered, shown[labeller_id] = shown[labeller_id], lease(labeller_id,
                                                                     shown[labeller_id])
        else:
            answered = lease(labeller_id, None)
        answer(labeller_id, answered)

    try:
        for i in range(warmup):
            round_trip(labellers[i % 10])
        figures = []
        for _ in range(repeats):
            start = time.process_time()
            for i in range(round_trips):
                round_trip(labellers[i % 10])
            figures.append((time.process_time() - start) / round_trips)
        per_call = None
        if calls:
            profile = cProfile.Profile()
            profile.enable()
            for i in range(round_trips):
                round_trip(labellers[i % 10])
            profile.disable()
            per_call = pstats.Stats(profile).total_calls / round_trips  # type: ignore[attr-defined]
    finally:
        if client is not None:
            client.close()
        engine.dispose()
        shutil.rmtree(tmp, ignore_errors=True)
    return figures, per_call


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--history", type=int, nargs="+", default=[0, 10_000, 100_000],
                        help="labels of an older run stored before timing, one database each")
    parser.add_argument("--round-trips", type=int, default=500, help="per repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--page", action="store_true",
                        help="as the label page asks: next with the run's id and ahead_of the "
                        "pair shown (its preload), then the answer to the pair shown")
    parser.add_argument("--app", action="store_true",
                        help="through the app's ASGI callable (routing, validation, JSON; no HTTP)")
    parser.add_argument("--calls", action="store_true",
                        help="also count function calls per round trip (cProfile)")
    args = parser.parse_args()
    if min(args.history) < 0 or args.round_trips < 1 or args.repeats < 1:
        parser.error("--history must be >= 0, --round-trips and --repeats >= 1")
    what = "the app's request handling" if args.app else "queue work"
    print(f"{what} per round trip (lease + submit{', as the page asks' if args.page else ''}"
          f", one thread, SQLite), "
          f"{args.round_trips} round trips x {args.repeats}; load average "
          f"{os.getloadavg()[0]:.2f}; checkout {os.environ.get('PYTHONPATH', '.')}")
    print(f"{'older labels':>13} {'CPU ms per round trip (median)':>32} {'range':>16}"
          + (f" {'calls per round trip':>21}" if args.calls else ""))
    for history in args.history:
        seconds, calls = per_round_trip(history, args.round_trips, args.repeats, args.page,
                                        args.app, args.calls)
        figures = [1000 * f for f in seconds]
        print(f"{history:>13} {statistics.median(figures):>32.3f} "
              f"{min(figures):>7.3f}-{max(figures):<8.3f}"
              + (f" {calls:>21.0f}" if calls is not None else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

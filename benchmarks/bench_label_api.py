"""Label API round trip under concurrent labellers: GET /api/label/next + POST /api/label/{id}.

The real server (`uvicorn server.app:app`, one worker process) runs as a subprocess on a fresh
SQLite queue in a temporary folder and is reached over loopback. Labellers and a human-taught
run are made over REST with the operator token; the run is then claimed, given its queries and
their clips directly through `labelqueue`, as the trainer's worker does. N labellers (asyncio
tasks, one httpx connection each, no pause unless --think-ms) loop next -> submit until the
queue is drained: a warm-up round first, then the timed one. A round trip is next + submit,
timed by the client. Afterwards the database is checked: one label per query, none twice, none
lost; the script exits 1 otherwise.

    .venv/bin/python benchmarks/bench_label_api.py                          # 50 x 3000, ~1.5 min
    .venv/bin/python benchmarks/bench_label_api.py --labellers 10 --queries 1000
    .venv/bin/python benchmarks/bench_label_api.py --think-ms 2000 --queries 500   # paced people
    .venv/bin/python benchmarks/bench_label_api.py --probe   # + where the server's time goes

`--probe` starts the same app through this script instead of `-m uvicorn`, with timers on every
request, SQLite's BEGIN IMMEDIATE (the wait for the write lock), each transaction and each SQL
statement; it prints them after the timed round. The probe's own cost is part of its figures.
"""

from __future__ import annotations

import argparse
import asyncio
import atexit
import json
import os
import random
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import select

from labelqueue import (
    Label,
    Query,
    QueryStatus,
    Run,
    claim_run,
    make_engine,
    push_queries,
    session_factory,
    set_clips,
)

ROOT = Path(__file__).resolve().parent.parent
OPERATOR_TOKEN = "bench-operator-token-0123456789"
SECRET_KEY = "bench-secret-key-0123456789"
CHOICES = ("left", "right", "equal")
TARGET_P99_MS = 50.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def query_spec(round_: int, position: int) -> dict[str, Any]:
    """A query as the worker pushes it (the fields of tests/server/server_helpers.query_spec)."""
    return {
        "round": round_,
        "position": position,
        "segment_length": 50,
        "first_trajectory": 2 * position,
        "first_start": 10,
        "second_trajectory": 2 * position + 1,
        "second_start": 20,
        "first_segment_return": 1.0,
        "second_segment_return": 2.0,
        "first_trajectory_return": 10.0,
        "second_trajectory_return": 20.0,
        "model_p": 0.5,
        "score": 0.1,
    }


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine_ticks() -> tuple[int, int, int]:
    """(all, idle + iowait, steal) CPU ticks of the whole machine so far."""
    values = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return sum(values), values[3] + values[4], values[7] if len(values) > 7 else 0


# ---------------------------------------------------------------------------------------------
# The server


def start_server(tmp: Path, port: int, *, probe: bool, stats_file: Path) -> subprocess.Popen[bytes]:
    env = os.environ | {
        "SEPOA_DATABASE_URL": f"sqlite:///{tmp / 'queue.db'}",
        "SEPOA_DATA_DIR": str(tmp),
        "SEPOA_OPERATOR_TOKEN": OPERATOR_TOKEN,
        "SEPOA_SECRET_KEY": SECRET_KEY,
    }
    if probe:
        command = [sys.executable, __file__, "--serve-probe", "--port", str(port),
                   "--stats-file", str(stats_file)]
    else:
        command = [sys.executable, "-m", "uvicorn", "server.app:app", "--host", "127.0.0.1",
                   "--port", str(port), "--workers", "1", "--log-level", "warning",
                   "--no-access-log"]
    server = subprocess.Popen(command, cwd=ROOT, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit(f"the server exited with code {server.returncode} at start-up")
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=1).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    server.kill()
    raise SystemExit("the server did not answer /healthz within 60 s")


def stop_server(server: subprocess.Popen[bytes]) -> None:
    if server.poll() is None:
        server.send_signal(signal.SIGINT)  # uvicorn's graceful shutdown: the probe writes stats
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


# ---------------------------------------------------------------------------------------------
# Seeding: labellers and the run over REST, queries and clips as the worker would


def seed_rest(base: str, labellers: int, budget: int) -> tuple[list[str], int]:
    operator = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}
    with httpx.Client(base_url=base, headers=operator, timeout=30) as client:
        tokens = []
        for i in range(labellers):
            response = client.post("/api/labellers", json={"name": f"labeller-{i:03d}"})
            assert response.status_code == 201, response.text
            tokens.append(response.json()["token"])
        body = {"task": "dmc:cheetah_run", "algo": "pebble", "budget": budget,
                "preset": "small", "teacher": "human"}
        response = client.post("/api/runs", json=body)
        assert response.status_code == 201, response.text
        run_id: int = response.json()["id"]
    return tokens, run_id


def push_round(tmp: Path, url: str, run_id: int, round_: int, n: int) -> list[int]:
    """Push a round of `n` queries and attach a pair of small clip files to each."""
    engine = make_engine(url)
    try:
        with session_factory(engine)() as session:
            ids = push_queries(session, run_id=run_id,
                               queries=[query_spec(round_, i) for i in range(n)])
            for query_id in ids:
                keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
                for key in keys:
                    path = tmp / "clips" / key
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(b"\x00\x00\x00\x18ftypmp42 fake clip " + key.encode())
                set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    finally:
        engine.dispose()
    return ids


# ---------------------------------------------------------------------------------------------
# The load


@dataclass
class Tally:
    target: int
    round_trips: list[float] = field(default_factory=list)
    nexts: list[float] = field(default_factory=list)
    submits: list[float] = field(default_factory=list)
    label_ids: list[int] = field(default_factory=list)
    statuses: Counter[str] = field(default_factory=Counter)
    errors: list[str] = field(default_factory=list)


async def labeller(base: str, token: str, tally: Tally, rng: random.Random, think_s: float,
                   poll_s: float, deadline: float) -> None:
    headers = {"Authorization": f"Bearer {token}"}
    limits = httpx.Limits(max_connections=1, max_keepalive_connections=1)
    async with httpx.AsyncClient(base_url=base, headers=headers, limits=limits,
                                 timeout=60) as client:
        if think_s:
            # People do not all click at once: spread the first requests over a think time.
            await asyncio.sleep(rng.uniform(0, think_s))
        while len(tally.label_ids) < tally.target and time.monotonic() < deadline:
            t0 = time.perf_counter()
            response = await client.get("/api/label/next")
            t1 = time.perf_counter()
            tally.statuses[f"next {response.status_code}"] += 1
            if response.status_code == 204:
                # Others hold the last leases: poll until they have answered.
                await asyncio.sleep(poll_s)
                continue
            if response.status_code != 200:
                tally.errors.append(f"next: {response.status_code} {response.text[:200]}")
                await asyncio.sleep(0.02)
                continue
            query = response.json()
            if think_s:
                await asyncio.sleep(rng.expovariate(1 / think_s))
            body = {
                "choice": rng.choice(CHOICES),
                "left_is_first": query["left_is_first"],
                "shown_at": datetime.now(UTC).isoformat(),
            }
            t2 = time.perf_counter()
            response = await client.post(f"/api/label/{query['query_id']}", json=body)
            t3 = time.perf_counter()
            tally.statuses[f"submit {response.status_code}"] += 1
            if response.status_code != 201:
                tally.errors.append(f"submit {query['query_id']}: {response.status_code} "
                                    f"{response.text[:200]}")
                continue
            tally.label_ids.append(response.json()["id"])
            tally.nexts.append(t1 - t0)
            tally.submits.append(t3 - t2)
            tally.round_trips.append((t1 - t0) + (t3 - t2))


async def load(base: str, tokens: list[str], target: int, seed: int, think_s: float,
               poll_s: float, timeout_s: float) -> Tally:
    tally = Tally(target=target)
    deadline = time.monotonic() + timeout_s
    await asyncio.gather(*(
        labeller(base, token, tally, random.Random(seed * 1000 + i), think_s, poll_s, deadline)
        for i, token in enumerate(tokens)
    ))
    return tally


# ---------------------------------------------------------------------------------------------
# Checks


def verify(url: str, run_id: int, label_ids: list[int], pushed: int) -> list[str]:
    """What is wrong with the run's queries and labels after the load; empty when all is well.

    `label_ids`: the ids of every 201 response; `pushed`: how many queries the run was given.
    """
    problems: list[str] = []
    engine = make_engine(url)
    try:
        with session_factory(engine)() as session:
            queries = list(session.scalars(select(Query).where(Query.run_id == run_id)))
            labels = list(session.scalars(select(Label).where(Label.run_id == run_id)))
            run = session.get(Run, run_id)
            session.commit()
    finally:
        engine.dispose()
    assert run is not None
    if len(queries) != pushed:
        problems.append(f"the run has {len(queries)} queries, {pushed} were pushed")
    per_query = Counter(label.query_id for label in labels)
    pairs = Counter((label.query_id, label.labeller_id) for label in labels)
    stored = {label.id for label in labels}
    for query in queries:
        if query.needs_labels != 1:
            problems.append(f"query {query.id} wants {query.needs_labels} labels, not 1")
        if per_query[query.id] != 1:
            problems.append(f"query {query.id} has {per_query[query.id]} labels")
        if query.label_count != per_query[query.id]:
            problems.append(f"query {query.id} counts {query.label_count} labels, "
                            f"has {per_query[query.id]}")
        if query.status is not QueryStatus.LABELLED or query.lease_holder is not None:
            problems.append(f"query {query.id} is left {query.status} "
                            f"(lease holder {query.lease_holder})")
    problems += [f"query {q} has two labels by labeller {lab}"
                 for (q, lab), n in pairs.items() if n > 1]
    answered = Counter(label_ids)
    problems += [f"label {i} was answered 201 {n} times" for i, n in answered.items() if n > 1]
    problems += [f"label {i} answered 201 is not stored" for i in set(answered) - stored]
    problems += [f"label {i} is stored but no request got it" for i in stored - set(answered)]
    if run.labels_used != len(labels):
        problems.append(f"run labels_used is {run.labels_used}, it has {len(labels)} labels")
    return problems


# ---------------------------------------------------------------------------------------------
# The probe: the same app, with timers (only with --probe)


def serve_probe(port: int, stats_file: Path) -> None:
    """Run `server.app` with timers on requests, transactions and statements; dump them at exit."""
    import uvicorn
    from sqlalchemy import Engine, event
    from sqlalchemy.orm import Session

    from server.app import create_app

    samples: dict[str, list[float]] = defaultdict(list)
    local = threading.local()
    lock = threading.Lock()

    def add(key: str, value: float) -> None:
        with lock:
            samples[key].append(value)

    @event.listens_for(Engine, "before_cursor_execute")
    def _before(conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        conn.info["probe_t0"] = time.perf_counter()

    @event.listens_for(Engine, "after_cursor_execute")
    def _after(conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        now = time.perf_counter()
        took = now - conn.info.pop("probe_t0", now)
        if statement.startswith("BEGIN"):
            add("BEGIN IMMEDIATE (write-lock wait)", took)
            local.tx_start = now
        else:
            add("SQL statement", took)
            local.statements = getattr(local, "statements", 0) + 1

    @event.listens_for(Engine, "commit")
    def _commit(_conn: Any) -> None:
        local.commit_start = time.perf_counter()

    @event.listens_for(Engine, "rollback")
    def _rollback(_conn: Any) -> None:
        local.commit_start = time.perf_counter()

    @event.listens_for(Session, "after_transaction_end")
    def _end(_session: Any, transaction: Any) -> None:
        if transaction.parent is not None or getattr(local, "commit_start", None) is None:
            return
        now = time.perf_counter()
        add("COMMIT", now - local.commit_start)
        if getattr(local, "tx_start", None) is not None:
            add("transaction (lock held)", now - local.tx_start)
            add("statements per transaction", getattr(local, "statements", 0))
        local.commit_start = local.tx_start = None
        local.statements = 0

    app = create_app()

    async def timed(scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await app(scope, receive, send)
            return
        path = scope["path"]
        kind = ("next" if path.endswith("/next") else "submit"
                if path.startswith("/api/label/") else "other")
        start = time.perf_counter()
        await app(scope, receive, send)
        add(f"server time {kind}", time.perf_counter() - start)

    def dump() -> None:
        with lock:
            stats_file.write_text(json.dumps(samples))

    atexit.register(dump)
    uvicorn.run(timed, host="127.0.0.1", port=port, log_level="warning", access_log=False,
                lifespan="on")


def print_probe(stats_file: Path, round_trips: int) -> None:
    if not stats_file.exists():
        print("probe: no stats were written")
        return
    samples: dict[str, list[float]] = json.loads(stats_file.read_text())
    print(f"\nprobe (server side, warm-up and timed rounds together; per round trip = "
          f"total / {round_trips} timed round trips):")
    print(f"{'what':<36} {'count':>7} {'p50 ms':>8} {'p99 ms':>8} {'total s':>8}")
    for key, values in sorted(samples.items()):
        if not values:
            continue
        if key == "statements per transaction":
            print(f"{key:<36} {len(values):>7} {statistics.median(values):>8.0f} "
                  f"{sorted(values)[int(0.99 * (len(values) - 1))]:>8.0f}")
            continue
        ordered = sorted(values)
        print(f"{key:<36} {len(values):>7} {1000 * statistics.median(ordered):>8.2f} "
              f"{1000 * ordered[int(0.99 * (len(ordered) - 1))]:>8.2f} {sum(values):>8.2f}")


# ---------------------------------------------------------------------------------------------


def percentile(ordered: list[float], q: float) -> float:
    """Nearest-rank percentile of an ascending list."""
    return ordered[max(0, min(len(ordered) - 1, round(q * len(ordered) + 0.5) - 1))]


def server_flavour() -> str:
    parts = []
    for module, name in (("uvloop", "uvloop"), ("httptools", "httptools")):
        try:
            __import__(module)
            parts.append(name)
        except ImportError:
            pass
    return " + ".join(parts) or "asyncio + h11"


@dataclass
class Measured:
    """The timed round, and what the machine did meanwhile."""

    tally: Tally
    warm_label_ids: list[int]
    run_id: int
    seconds: float
    server_cpu_s: float
    client_cpu_s: float
    machine_busy: float
    machine_steal: float


def run_rounds(args: argparse.Namespace, tmp: Path, url: str) -> Measured:
    """Start the server, seed it, run the warm-up and the timed round; stop the server."""
    port = free_port()
    server = start_server(tmp, port, probe=args.probe, stats_file=tmp / "probe.json")
    try:
        base = f"http://127.0.0.1:{port}"
        tokens, run_id = seed_rest(base, args.labellers, args.warmup + args.queries)
        engine = make_engine(url)
        with session_factory(engine)() as session:
            claimed = claim_run(session, worker_id="bench-worker")
        engine.dispose()
        assert claimed is not None and claimed.id == run_id, claimed

        push_round(tmp, url, run_id, 0, args.warmup)
        warm = asyncio.run(load(base, tokens, args.warmup, args.seed + 1, 0.0,
                                args.poll_ms / 1000, args.timeout))
        push_round(tmp, url, run_id, 1, args.queries)
        server_cpu, client_cpu = cpu_seconds(server.pid), time.process_time()
        ticks = machine_ticks()
        start = time.perf_counter()
        tally = asyncio.run(load(base, tokens, args.queries, args.seed, args.think_ms / 1000,
                                 args.poll_ms / 1000, args.timeout))
        seconds = time.perf_counter() - start
        all_ticks, idle, steal = (b - a for a, b in zip(ticks, machine_ticks(), strict=True))
        server_cpu = cpu_seconds(server.pid) - server_cpu
        client_cpu = time.process_time() - client_cpu
    finally:
        stop_server(server)
    tally.errors += [f"warm-up: {error}" for error in warm.errors]
    return Measured(tally, warm.label_ids, run_id, seconds, server_cpu, client_cpu,
                    1 - idle / max(1, all_ticks), steal / max(1, all_ticks))


def report(args: argparse.Namespace, m: Measured) -> None:
    tally, n = m.tally, max(1, len(m.tally.round_trips))
    print(f"label round trip (GET /api/label/next + POST /api/label/{{id}}), SQLite, loopback: "
          f"{args.labellers} labellers, {args.queries} queries (+{args.warmup} warm-up), "
          f"think time {args.think_ms:g} ms")
    print(f"server: 1 uvicorn worker process ({server_flavour()}"
          f"{', probe' if args.probe else ', no access log'}); {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}, machine busy {m.machine_busy:.0%}, "
          f"CPU time stolen by the host {m.machine_steal:.0%}")
    print(f"{'':<14} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for name, values in (("round trip", tally.round_trips), ("next", tally.nexts),
                         ("submit", tally.submits)):
        ordered = sorted(values) or [float("nan")]
        cells = [percentile(ordered, q) for q in (0.5, 0.9, 0.99)] + [ordered[-1]]
        print(f"{name:<14} " + " ".join(f"{1000 * v:>8.1f}" for v in cells))
    rate = len(tally.label_ids) / m.seconds
    conflicts = tally.statuses["next 409"] + tally.statuses["submit 409"]
    print(f"{rate:.0f} labels/s ({len(tally.label_ids)} in {m.seconds:.1f} s); "
          f"204s: {tally.statuses['next 204']}, 409s: {conflicts}, "
          f"other errors: {len(tally.errors) - conflicts}")
    print(f"CPU per round trip: server {1000 * m.server_cpu_s / n:.2f} ms "
          f"({m.server_cpu_s / m.seconds:.0%} of a core), client "
          f"{1000 * m.client_cpu_s / n:.2f} ms ({m.client_cpu_s / m.seconds:.0%})")
    if not args.think_ms and rate:
        # Little's law for a closed loop: labellers = rate x (round trip + the client's gap).
        print(f"closed loop, no think time: {args.labellers} labellers / {rate:.0f} per s = "
              f"{1000 * args.labellers / rate:.0f} ms per cycle; p99 <= {TARGET_P99_MS:g} ms "
              f"needs >= {1000 * args.labellers / TARGET_P99_MS:.0f} round trips/s")
    p99 = 1000 * percentile(sorted(tally.round_trips) or [float("inf")], 0.99)
    print(f"target: p99 <= {TARGET_P99_MS:g} ms -> {'met' if p99 <= TARGET_P99_MS else 'missed'}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--labellers", type=int, default=50)
    parser.add_argument("--queries", type=int, default=3000, help="timed round's queries")
    parser.add_argument("--warmup", type=int, default=250, help="warm-up round's queries")
    parser.add_argument("--think-ms", type=float, default=0.0,
                        help="mean pause between next and submit (exponential); 0: none")
    parser.add_argument("--poll-ms", type=float, default=2000.0,
                        help="wait after a 204 (nothing free: others hold the last leases); "
                        "the label page's POLL_MS")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per round, at most")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--probe", action="store_true",
                        help="serve through the probe (timers on requests, lock waits, SQL)")
    parser.add_argument("--serve-probe", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--stats-file", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_probe:
        serve_probe(args.port, args.stats_file)
        return 0

    with tempfile.TemporaryDirectory(prefix="bench-label-api-") as tmp_name:
        tmp = Path(tmp_name)
        url = f"sqlite:///{tmp / 'queue.db'}"
        m = run_rounds(args, tmp, url)
        report(args, m)
        if args.probe:
            print_probe(tmp / "probe.json", len(m.tally.round_trips))
        answered = m.warm_label_ids + m.tally.label_ids
        problems = verify(url, m.run_id, answered, args.warmup + args.queries)
        problems += [f"request failed: {error}" for error in m.tally.errors[:20]]
        if len(m.warm_label_ids) != args.warmup or len(m.tally.label_ids) != args.queries:
            problems.append(f"rounds answered {len(m.warm_label_ids)} of {args.warmup} and "
                            f"{len(m.tally.label_ids)} of {args.queries} queries")
    if problems:
        print(f"FAILED: {len(problems)} problems with the labels:", file=sys.stderr)
        for problem in problems[:30]:
            print(f"  {problem}", file=sys.stderr)
        return 1
    print(f"verified in the database: {len(answered)} queries with exactly one label each, "
          f"every 201's label stored, labels_used {len(answered)}, none left leased or "
          "pending: no duplicated or lost labels")
    return 0


if __name__ == "__main__":
    sys.exit(main())

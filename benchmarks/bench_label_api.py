"""Label API round trip under concurrent labellers: GET /api/label/next + POST /api/label/{id}.

The real server (`uvicorn server.app:app`) runs as a subprocess on a fresh queue database (SQLite
in a temporary folder, or a fresh database on PostgreSQL) and is reached over loopback. Labellers
and a human-taught run are made over REST with the operator token; the run is claimed and given a
warm-up round directly through `labelqueue`. Then, for the timed round, and all at once:

- N labellers (asyncio tasks, one keep-alive connection each) loop next -> submit (a pause of
  --think-ms between them, exponential, if given) until the round is answered;
- a worker process (this script again, as the trainer's worker would) pushes the round's queries
  in rounds of --round-size as the labellers answer them (it reads their labels twice a second),
  heartbeats every second, writes an episodes metric row every second and an eval row every
  --eval-every-s, and consumes the labels every 5 s;
- --pollers dashboard pages poll the run page's endpoints over HTTP every 5 s (run, three metric
  streams and the label throughput, the curves figure when an evaluation is new), as run.js does;
- with --export-labels N, an older run with N labels is seeded first, and the whole label
  database is exported over HTTP (`/api/export?format=jsonl`) while the labellers work.

A round trip is next + submit, timed by the client. Afterwards the database is checked: one
label per query, every 201's label stored, none twice, none lost; the script exits 1 otherwise.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_label_api.py --think-ms 2000 --queries 1500
    PYTHONPATH=. .venv/bin/python benchmarks/bench_label_api.py                 # closed loop
    PYTHONPATH=. .venv/bin/python benchmarks/bench_label_api.py --export-labels 100000
    bash scripts/with_postgres.sh .venv/bin/python benchmarks/bench_label_api.py --database postgres
    PYTHONPATH=. .venv/bin/python benchmarks/bench_label_api.py --probe --profile   # where it goes

PYTHONPATH names the checkout whose server, worker and queue package are measured (the server and
worker subprocesses are given it too), so an older checkout can be measured by the same script.
`--probe` serves the same app through this script (one process) with timers on every request,
SQLite's BEGIN IMMEDIATE (the wait for the write lock), each write transaction and statement;
`--profile` adds cProfile (CPU time of each server thread) and prints the top entries. Both cost
a little themselves.
"""

from __future__ import annotations

import argparse
import asyncio
import atexit
import contextlib
import cProfile
import json
import os
import pstats
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from sqlalchemy import create_engine, insert, select

from labelqueue import (
    Label,
    Query,
    QueryStatus,
    Run,
    claim_run,
    consume_labels,
    heartbeat,
    labels_for_queries,
    make_engine,
    migrate,
    push_queries,
    session_factory,
    write_metrics,
)
from runvocab.answers import answer_of_click

ROOT = Path(__file__).resolve().parent.parent
OPERATOR_TOKEN = "bench-operator-token-0123456789"
SECRET_KEY = "bench-secret-key-0123456789"
CHOICES = ("left", "right", "equal")
TARGET_P99_MS = 50.0
WORKER_ID = "bench-worker"
PAGE_POLL_S = 5.0
"""the run page's refresh period (web/static/run.js)"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def query_spec(round_: int, position: int, clips: tuple[str, str] | None = None,
               needs: int = 1) -> dict[str, Any]:
    """A query as the worker pushes it (the fields of tests/server/server_helpers.query_spec),
    wanting `needs` labellers' answers."""
    spec = {
        "needs_labels": needs,
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
    if clips is not None:
        spec["first_clip"], spec["second_clip"] = clips
    return spec


def write_clips(clips_dir: Path, run_id: int, round_: int, position: int) -> tuple[str, str]:
    """A pair of small clip files, as rendering would leave them; their storage keys."""
    keys = (f"run{run_id}/r{round_}-{position}-a.mp4", f"run{run_id}/r{round_}-{position}-b.mp4")
    for key in keys:
        path = clips_dir / key
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"\x00\x00\x00\x18ftypmp42 fake clip " + key.encode())
    return keys


# ---------------------------------------------------------------------------------------------
# Processes: CPU time and memory from /proc


def _stat_fields(pid: int) -> list[str]:
    return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()


def process_tree(pid: int) -> list[int]:
    """`pid` and its descendants (uvicorn's worker processes)."""
    found, todo = [], [pid]
    while todo:
        current = todo.pop()
        found.append(current)
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{current}/task").iterdir():
                todo += [int(child) for child in (task / "children").read_text().split()]
    return found


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU time of these processes so far (those that have exited count 0)."""
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError):
            fields = _stat_fields(pid)
            total += int(fields[11]) + int(fields[12])
    return total / os.sysconf("SC_CLK_TCK")


def postgres_pids() -> list[int]:
    """Every PostgreSQL server process on the machine (the cluster's backends)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                if (entry / "comm").read_text().strip() == "postgres":
                    pids.append(int(entry.name))
    return pids


def rss_mib(pids: list[int]) -> float:
    """Resident memory of these processes now, MiB."""
    total = 0
    for pid in pids:
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
    return total / 1024


def machine_ticks() -> tuple[int, int, int]:
    """(all, idle + iowait, steal) CPU ticks of the whole machine so far."""
    values = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return sum(values), values[3] + values[4], values[7] if len(values) > 7 else 0


# ---------------------------------------------------------------------------------------------
# The database


@contextlib.contextmanager
def fresh_database(args: argparse.Namespace, tmp: Path) -> Iterator[str]:
    """The URL of an empty, migrated queue database: SQLite in `tmp`, or a new PostgreSQL
    database next to the one SEPOA_TEST_POSTGRES_URL names (dropped afterwards)."""
    if args.database == "sqlite":
        url = f"sqlite:///{tmp / 'queue.db'}"
        migrate(url)
        yield url
        return
    base = os.environ.get("SEPOA_TEST_POSTGRES_URL")
    if not base:
        raise SystemExit("--database postgres needs SEPOA_TEST_POSTGRES_URL: run it under "
                         "scripts/with_postgres.sh")
    name = f"bench_{uuid.uuid4().hex[:10]}"
    admin = create_engine(base, isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.exec_driver_sql(f'CREATE DATABASE "{name}"')
    url = base.replace("/sepoa_test", f"/{name}", 1)
    try:
        migrate(url)  # before the server starts: its worker processes would race to migrate
        yield url
    finally:
        with admin.connect() as connection:
            connection.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        admin.dispose()


def seed_history(url: str, labeller_id: int, n: int) -> None:
    """An older, finished run with `n` answered queries (one label each), for the export."""
    engine = make_engine(url)
    now = datetime.now(UTC)
    with engine.begin() as connection:
        run_id = connection.execute(insert(Run).values(
            name="history", task="dmc:cheetah_run", algo="pebble", preset="small", seed=1,
            config={}, teacher="human", teacher_params={}, budget=n, labels_used=n, step=0,
            progress={}, status="finished", created_at=now)).inserted_primary_key[0]
    for start in range(0, n, 10_000):
        positions = range(start, min(n, start + 10_000))
        with engine.begin() as connection:
            rows = [query_spec(position // 100, position) | {
                "run_id": run_id, "needs_labels": 1, "label_count": 1, "status": "labelled",
                "created_at": now} for position in positions]
            ids = connection.execute(
                insert(Query).returning(Query.id, sort_by_parameter_order=True), rows
            ).scalars().all()
            labels = [{
                "query_id": query_id, "run_id": run_id, "labeller_id": labeller_id,
                "choice": CHOICES[query_id % 3], "left_is_first": bool(query_id % 2),
                "answer": answer_of_click(CHOICES[query_id % 3], bool(query_id % 2)),
                "source": "human",
                "shown_at": now - timedelta(seconds=5), "answered_at": now,
            } for query_id in ids]
            connection.execute(insert(Label), labels)
    engine.dispose()


# ---------------------------------------------------------------------------------------------
# The server


def start_server(
    args: argparse.Namespace, tmp: Path, url: str, port: int
) -> subprocess.Popen[bytes]:
    env = os.environ | {
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "SEPOA_DATABASE_URL": url,
        "SEPOA_DATA_DIR": str(tmp),
        "SEPOA_OPERATOR_TOKEN": OPERATOR_TOKEN,
        "SEPOA_SECRET_KEY": SECRET_KEY,  # one side order across worker processes
        # A closed loop asks faster than the per-labeller lease limit allows (2/s): measured is
        # the label API's own cost, so the limit is lifted unless the caller sets one.
        "SEPOA_LEASE_PER_S": os.environ.get("SEPOA_LEASE_PER_S", "100000"),
        "SEPOA_LEASE_BURST": os.environ.get("SEPOA_LEASE_BURST", "1000000"),
    }
    if args.probe or args.profile:
        command = [sys.executable, __file__, "--serve-probe", "--port", str(port),
                   "--stats-file", str(tmp / "probe.json")]
        if args.profile:
            command.append("--profile")
    else:
        command = [sys.executable, "-m", "uvicorn", "server.app:app", "--host", "127.0.0.1",
                   "--port", str(port), "--workers", str(args.workers), "--log-level",
                   "warning", "--no-access-log"]
    server = subprocess.Popen(command, cwd=ROOT, env=env)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit(f"the server exited with code {server.returncode} at start-up")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as sock:
                sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: bench\r\nConnection: close\r\n\r\n")
                if sock.recv(64).startswith(b"HTTP/1.1 200"):
                    return server
        except OSError:
            pass
        time.sleep(0.1)
    server.kill()
    raise SystemExit("the server did not answer /healthz within 60 s")


def stop_process(process: subprocess.Popen[bytes]) -> None:
    if process.poll() is None:
        process.send_signal(signal.SIGINT)  # uvicorn's graceful shutdown: the probe writes stats
        try:
            process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


# ---------------------------------------------------------------------------------------------
# A minimal keep-alive HTTP/1.1 client: httpx took 3-4 ms of CPU per request, as much as the
# server, and the load generator shares the machine's two cores with it.


class Http:
    IDLE_S = 4.0
    """uvicorn closes a keep-alive connection idle for 5 s: open a new one before that"""

    def __init__(self, port: int, token: str):
        self.port = port
        self.auth = f"Host: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n"
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.used = 0.0

    async def _send(self, method: str, path: str, body: bytes | None) -> asyncio.StreamReader:
        idle = time.monotonic() - self.used > self.IDLE_S
        if self.reader is None or self.writer is None or self.writer.is_closing() or idle:
            await self.close()
            self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)
        self.used = time.monotonic()
        head = f"{method} {path} HTTP/1.1\r\n{self.auth}"
        if body is not None:
            head += f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
        self.writer.write(head.encode() + b"\r\n" + (body or b""))
        return self.reader

    async def _head(self, reader: asyncio.StreamReader) -> tuple[int, int | None]:
        status = int((await reader.readline()).split()[1])
        length: int | None = 0 if status in (204, 304) else None
        while (line := await reader.readline()) not in (b"\r\n", b""):
            name, _, value = line.partition(b":")
            if name.strip().lower() == b"content-length":
                length = int(value)
        return status, length

    async def request(self, method: str, path: str, body: Any = None) -> tuple[int, bytes]:
        data = None if body is None else json.dumps(body).encode()
        reader = await self._send(method, path, data)
        status, length = await self._head(reader)
        if length is None:
            raise RuntimeError(f"{method} {path}: no Content-Length in the response")
        body = await reader.readexactly(length)
        self.used = time.monotonic()
        return status, body

    async def drain(self, path: str) -> tuple[int, int]:
        """GET a large body, reading it in blocks and keeping none; (status, bytes read)."""
        reader = await self._send("GET", path, None)
        status, length = await self._head(reader)
        assert length is not None
        left = length
        while left:
            left -= len(await reader.read(min(left, 1 << 16)))
        self.used = time.monotonic()
        return status, length

    async def close(self) -> None:
        writer, self.reader, self.writer = self.writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


def seed_rest(port: int, labellers: int, budget: int) -> tuple[list[str], int]:
    async def seed() -> tuple[list[str], int]:
        client = Http(port, OPERATOR_TOKEN)
        tokens = []
        for i in range(labellers):
            status, body = await client.request("POST", "/api/labellers",
                                                {"name": f"labeller-{i:03d}"})
            assert status == 201, body
            tokens.append(json.loads(body)["token"])
        spec = {"task": "dmc:cheetah_run", "algo": "pebble", "budget": budget,
                "preset": "small", "teacher": "human"}
        status, body = await client.request("POST", "/api/runs", spec)
        assert status == 201, body
        await client.close()
        return tokens, int(json.loads(body)["id"])

    return asyncio.run(seed())


# ---------------------------------------------------------------------------------------------
# The worker process: the trainer's side of the queue, as a second process on the database


def serve_worker(args: argparse.Namespace) -> None:
    """Push `--queries` queries (clips rendered first) in rounds as labellers answer them, keeping
    at least `low_water` open; read the open queries' labels twice a second, as the trainer waits
    for a round; heartbeat and write an episodes row every second and an eval row every
    --eval-every-s; consume the labels every 5 s. Runs until SIGTERM; writes its timings."""
    sessions = session_factory(make_engine(args.url))
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    timings: dict[str, list[float]] = defaultdict(list)
    clips_dir = Path(args.clips_dir)
    low_water = max(3 * args.labellers, 2 * args.round_size)
    open_ids: set[int] = set()
    pushed = step = 0
    round_ = 1
    last_beat = last_eval = last_consume = 0.0

    def timed(name: str, op: Any, **kwargs: Any) -> Any:
        with sessions() as session:
            start = time.perf_counter()
            result = op(session, **kwargs)
            timings[name].append(time.perf_counter() - start)
        return result

    while not stop.is_set():
        now = time.monotonic()
        if open_ids:
            answered = timed("labels_for_queries", labels_for_queries, query_ids=sorted(open_ids))
            counts = Counter(label.query_id for label in answered)
            open_ids -= {query for query, n in counts.items() if n >= args.labels_per_query}
        if pushed < args.queries and len(open_ids) < low_water:
            n = min(args.round_size, args.queries - pushed)
            specs = [query_spec(round_, i, write_clips(clips_dir, args.run_id, round_, i),
                                args.labels_per_query) for i in range(n)]
            open_ids |= set(timed("push_queries", push_queries, run_id=args.run_id,
                                  queries=specs))
            pushed += n
            round_ += 1
            if pushed == n or pushed == args.queries:
                print("ready" if pushed == n else "all pushed", flush=True)
        if now - last_beat >= 1.0:
            step += 1000
            timed("heartbeat", heartbeat, run_id=args.run_id, worker_id=WORKER_ID, step=step,
                  progress={"round": round_, "pushed": pushed, "open": len(open_ids)})
            timed("write_metrics", write_metrics, run_id=args.run_id, stream="episodes",
                  step=step, values={"return": step / 1000, "length": 1000})
            last_beat = now
        if now - last_eval >= args.eval_every_s:
            timed("write_metrics", write_metrics, run_id=args.run_id, stream="eval", step=step,
                  values={"return": step / 1000})
            last_eval = now
        if now - last_consume >= 5.0:
            timed("consume_labels", consume_labels, run_id=args.run_id)
            last_consume = now
        stop.wait(0.5 if pushed == args.queries else 0.2)
    Path(args.stats_file).write_text(json.dumps(timings))


def start_worker(args: argparse.Namespace, url: str, tmp: Path,
                 run_id: int) -> subprocess.Popen[bytes]:
    command = [sys.executable, __file__, "--serve-worker", "--url", url, "--run-id", str(run_id),
               "--clips-dir", str(tmp / "clips"), "--queries", str(args.queries),
               "--round-size", str(args.round_size), "--labellers", str(args.labellers),
               "--eval-every-s", str(args.eval_every_s),
               "--labels-per-query", str(args.labels_per_query), "--stats-file",
               str(tmp / "worker.json")]
    env = os.environ | {
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    worker = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE)
    assert worker.stdout is not None
    if worker.stdout.readline().strip() != b"ready":
        raise SystemExit(f"the worker process did not start (code {worker.wait()})")
    return worker


def push_warmup(url: str, tmp: Path, run_id: int, n: int, needs: int) -> None:
    engine = make_engine(url)
    with session_factory(engine)() as session:
        claimed = claim_run(session, worker_id=WORKER_ID)
        assert claimed is not None and claimed.id == run_id, claimed
        specs = [query_spec(0, i, write_clips(tmp / "clips", run_id, 0, i), needs)
                 for i in range(n)]
        push_queries(session, run_id=run_id, queries=specs)
    engine.dispose()


# ---------------------------------------------------------------------------------------------
# The load


@dataclass
class Tally:
    target: int
    round_trips: list[tuple[float, float]] = field(default_factory=list)
    """(start, seconds) of each answered round trip"""
    nexts: list[float] = field(default_factory=list)
    submits: list[float] = field(default_factory=list)
    label_ids: list[int] = field(default_factory=list)
    statuses: Counter[str] = field(default_factory=Counter)
    errors: list[str] = field(default_factory=list)
    pages: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    """dashboard request times by endpoint"""
    export: dict[str, float] = field(default_factory=dict)
    done: asyncio.Event = field(default_factory=asyncio.Event)


async def labeller(port: int, token: str, tally: Tally, rng: random.Random, think_s: float,
                   poll_s: float, deadline: float) -> None:
    client = Http(port, token)
    if think_s:
        # People do not all click at once: spread the first requests over a think time.
        await asyncio.sleep(rng.uniform(0, think_s))
    while len(tally.label_ids) < tally.target and time.monotonic() < deadline:
        t0 = time.perf_counter()
        status, body = await client.request("GET", "/api/label/next")
        t1 = time.perf_counter()
        tally.statuses[f"next {status}"] += 1
        if status == 204:
            # Others hold the last leases, or the worker has not pushed more yet: poll.
            await asyncio.sleep(poll_s)
            continue
        if status != 200:
            tally.errors.append(f"next: {status} {body[:200]!r}")
            await asyncio.sleep(0.02)
            continue
        query = json.loads(body)
        if think_s:
            await asyncio.sleep(rng.expovariate(1 / think_s))
        answer = {
            "choice": rng.choice(CHOICES),
            "left_is_first": query["left_is_first"],
            "shown_at": datetime.now(UTC).isoformat(),
        }
        t2 = time.perf_counter()
        status, body = await client.request("POST", f"/api/label/{query['query_id']}", answer)
        t3 = time.perf_counter()
        tally.statuses[f"submit {status}"] += 1
        if status != 201:
            tally.errors.append(f"submit {query['query_id']}: {status} {body[:200]!r}")
            continue
        tally.label_ids.append(json.loads(body)["id"])
        tally.nexts.append(t1 - t0)
        tally.submits.append(t3 - t2)
        tally.round_trips.append((t0, (t1 - t0) + (t3 - t2)))
    await client.close()


async def dashboard(port: int, run_id: int, tally: Tally, offset_s: float) -> None:
    """One open run page: what web/static/run.js fetches every 5 s."""
    client = Http(port, OPERATOR_TOKEN)
    evals_seen = -1
    await asyncio.sleep(offset_s)

    async def get(name: str, path: str) -> bytes:
        start = time.perf_counter()
        status, body = await client.request("GET", path)
        tally.pages[name].append(time.perf_counter() - start)
        if status != 200:
            tally.errors.append(f"page {path}: {status} {body[:200]!r}")
        return body

    while not tally.done.is_set():
        await get("run", f"/api/runs/{run_id}")
        # The page's four reads go out together; one connection here sends them in turn.
        for stream in ("episodes", "eval", "rounds"):
            body = await get("metrics", f"/api/runs/{run_id}/metrics?stream={stream}")
            if stream == "eval" and len(json.loads(body)) != evals_seen:
                evals_seen = len(json.loads(body))
                await get("curves.png", f"/api/runs/{run_id}/curves.png?metric=return")
        await get("throughput", f"/api/runs/{run_id}/throughput?bucket_s=60")
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(tally.done.wait(), PAGE_POLL_S)
    await client.close()


async def exporter(port: int, tally: Tally, server_pids: list[int]) -> None:
    """Export every label once, a second after the labellers started; note time, size, memory."""
    await asyncio.sleep(1.0)
    client = Http(port, OPERATOR_TOKEN)
    peak = before = rss_mib(server_pids)

    async def watch() -> None:
        nonlocal peak
        while True:
            peak = max(peak, rss_mib(server_pids))
            await asyncio.sleep(0.1)

    watcher = asyncio.ensure_future(watch())
    start = time.perf_counter()
    status, size = await client.drain("/api/export?format=jsonl")
    tally.export = {"start": start, "end": time.perf_counter(), "bytes": size,
                    "status": status, "rss_before_mib": before, "rss_peak_mib": peak}
    watcher.cancel()
    await client.close()


async def load(args: argparse.Namespace, port: int, tokens: list[str], target: int, seed: int,
               *, run_id: int, pages: bool, server_pids: list[int]) -> Tally:
    tally = Tally(target=target)
    deadline = time.monotonic() + args.timeout
    think_s, poll_s = args.think_ms / 1000, args.poll_ms / 1000
    side = []
    if pages:
        side += [
            asyncio.ensure_future(dashboard(port, run_id, tally, i * PAGE_POLL_S / args.pollers))
            for i in range(args.pollers)
        ]
        if args.export_labels:
            side.append(asyncio.ensure_future(exporter(port, tally, server_pids)))
    await asyncio.gather(*(
        labeller(port, token, tally, random.Random(seed * 1000 + i), think_s, poll_s, deadline)
        for i, token in enumerate(tokens)
    ))
    tally.done.set()
    await asyncio.gather(*side)
    return tally


def run_load(*coroutine_args: Any, **kwargs: Any) -> Tally:
    try:
        import uvloop
    except ImportError:
        return asyncio.run(load(*coroutine_args, **kwargs))
    return uvloop.run(load(*coroutine_args, **kwargs))


# ---------------------------------------------------------------------------------------------
# Checks


def verify(url: str, run_id: int, label_ids: list[int], pushed: int, k: int) -> list[str]:
    """What is wrong with the run's queries and labels after the load; empty when all is well:
    every query answered by exactly `k` labellers, none twice by one, every 201 stored once.

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
        if query.needs_labels != k:
            problems.append(f"query {query.id} wants {query.needs_labels} labels, not {k}")
        if per_query[query.id] != k:
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
# The probe: the same app, with timers (only with --probe) and cProfile (--profile)


def serve_probe(port: int, stats_file: Path, profile: bool) -> None:
    """Run `server.app` with timers on requests, transactions and statements (and cProfile on
    every thread); dump them at exit."""
    import uvicorn
    from sqlalchemy import Engine, event

    from server.app import create_app

    samples: dict[str, list[float]] = defaultdict(list)
    local = threading.local()
    lock = threading.Lock()
    profiles: list[cProfile.Profile] = []

    def add(key: str, value: float) -> None:
        with lock:
            samples[key].append(value)

    if profile:
        def start_profile(*_args: Any) -> None:  # the first event of each new thread
            sys.setprofile(None)
            thread_profile = cProfile.Profile(time.thread_time)
            with lock:
                profiles.append(thread_profile)
            thread_profile.enable()

        threading.setprofile(start_profile)
        main_profile = cProfile.Profile(time.thread_time)
        profiles.append(main_profile)
        main_profile.enable()

    @event.listens_for(Engine, "begin")  # class-level: runs before the engine's own BEGIN hook
    def _begin(conn: Any) -> None:
        read_only = conn.get_execution_options().get("labelqueue_read_only", False)
        local.begin_at = None if read_only else time.perf_counter()

    @event.listens_for(Engine, "before_cursor_execute")
    def _before(conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        now = conn.info["probe_t0"] = time.perf_counter()
        if getattr(local, "begin_at", None) is not None:  # the write transaction's first
            add("BEGIN IMMEDIATE (write-lock wait)", now - local.begin_at)
            local.tx_start, local.statements, local.begin_at = now, 0, None

    @event.listens_for(Engine, "after_cursor_execute")
    def _after(conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        now = time.perf_counter()
        add("SQL statement", now - conn.info.pop("probe_t0", now))
        local.statements = getattr(local, "statements", 0) + 1

    def _end(_conn: Any) -> None:
        if getattr(local, "tx_start", None) is not None:
            add("write transaction, to its COMMIT", time.perf_counter() - local.tx_start)
            add("statements per write transaction", local.statements)
        local.tx_start = None

    event.listen(Engine, "commit", _end)
    event.listen(Engine, "rollback", _end)

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
            if profiles:
                for thread_profile in profiles:
                    thread_profile.disable()
                merged = pstats.Stats(profiles[0])
                for thread_profile in profiles[1:]:
                    with contextlib.suppress(TypeError):  # a thread that never ran code
                        merged.add(thread_profile)
                merged.dump_stats(str(stats_file.with_suffix(".prof")))

    atexit.register(dump)
    uvicorn.run(timed, host="127.0.0.1", port=port, log_level="warning", access_log=False,
                lifespan="on")


def print_probe(stats_file: Path, round_trips: int, top: int) -> None:
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
        ordered = sorted(values)
        if key.startswith("statements per"):
            print(f"{key:<36} {len(values):>7} {statistics.median(values):>8.0f} "
                  f"{ordered[int(0.99 * (len(values) - 1))]:>8.0f}")
            continue
        print(f"{key:<36} {len(values):>7} {1000 * statistics.median(ordered):>8.2f} "
              f"{1000 * ordered[int(0.99 * (len(ordered) - 1))]:>8.2f} {sum(values):>8.2f}")
    profile = stats_file.with_suffix(".prof")
    if profile.exists():
        print(f"\ncProfile of every server thread (CPU time of each thread; warm-up and timed "
              f"rounds), top {top} by own time:")
        pstats.Stats(str(profile)).strip_dirs().sort_stats("tottime").print_stats(top)


# ---------------------------------------------------------------------------------------------


def percentile(ordered: list[float], q: float) -> float:
    """Nearest-rank percentile of an ascending list."""
    if not ordered:
        return float("nan")
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
    worker_cpu_s: float
    database_cpu_s: float | None
    client_cpu_s: float
    machine_busy: float
    machine_steal: float
    worker_timings: dict[str, list[float]]


def run_rounds(args: argparse.Namespace, tmp: Path, url: str) -> Measured:
    """Start the server, seed it, run the warm-up and the timed round; stop the server."""
    port = free_port()
    server = start_server(args, tmp, url, port)
    worker = None
    try:
        tokens, run_id = seed_rest(port, args.labellers, args.warmup + args.queries)
        if args.export_labels or args.history_labels:
            seed_history(url, labeller_id=1, n=args.export_labels or args.history_labels)
        k = args.labels_per_query
        push_warmup(url, tmp, run_id, args.warmup, k)
        warm = run_load(args, port, tokens, args.warmup * k, args.seed + 1, run_id=run_id,
                        pages=False, server_pids=[])
        server_pids = process_tree(server.pid)
        if args.worker:
            worker = start_worker(args, url, tmp, run_id)
        else:
            specs = [query_spec(1, i, write_clips(tmp / "clips", run_id, 1, i), k)
                     for i in range(args.queries)]
            with session_factory(make_engine(url))() as session:
                push_queries(session, run_id=run_id, queries=specs)
        database = postgres_pids() if args.database == "postgres" else []
        server_cpu, client_cpu = cpu_seconds(server_pids), time.process_time()
        worker_cpu = cpu_seconds([worker.pid]) if worker else 0.0
        database_cpu = {pid: cpu_seconds([pid]) for pid in database}
        ticks = machine_ticks()
        start = time.perf_counter()
        tally = run_load(args, port, tokens, args.queries * k, args.seed, run_id=run_id, pages=True,
                         server_pids=server_pids)
        seconds = time.perf_counter() - start
        all_ticks, idle, steal = (b - a for a, b in zip(ticks, machine_ticks(), strict=True))
        server_cpu = cpu_seconds(server_pids) - server_cpu
        worker_cpu = (cpu_seconds([worker.pid]) if worker else 0.0) - worker_cpu
        # Backends that started meanwhile count whole; one that ended meanwhile is not seen.
        database_used = sum(cpu_seconds([pid]) - database_cpu.get(pid, 0.0)
                            for pid in postgres_pids()) if database else 0.0
        client_cpu = time.process_time() - client_cpu
    finally:
        if worker is not None:
            worker.terminate()
            worker.wait(timeout=60)
        stop_process(server)
    tally.errors += [f"warm-up: {error}" for error in warm.errors]
    worker_file = tmp / "worker.json"
    worker_timings = json.loads(worker_file.read_text()) if worker_file.exists() else {}
    return Measured(tally, warm.label_ids, run_id, seconds, server_cpu, worker_cpu,
                    database_used if database else None, client_cpu,
                    1 - idle / max(1, all_ticks), steal / max(1, all_ticks), worker_timings)


def _row(name: str, values: list[float]) -> str:
    ordered = sorted(values)
    cells = [percentile(ordered, q) for q in (0.5, 0.9, 0.99)] + [ordered[-1] if ordered else 0]
    return f"{name:<14} " + " ".join(f"{1000 * v:>8.1f}" for v in cells) + f" {len(values):>7}"


def report(args: argparse.Namespace, m: Measured) -> None:
    tally, n = m.tally, max(1, len(m.tally.round_trips))
    processes = "1 process" if args.probe or args.profile else f"{args.workers} process"
    print(f"label round trip (GET /api/label/next + POST /api/label/{{id}}), {args.database}, "
          f"loopback: {args.labellers} labellers, {args.queries} queries (+{args.warmup} "
          f"warm-up), think time {args.think_ms:g} ms; {args.pollers} dashboard pages, worker "
          f"process {'on' if args.worker else 'off'}"
          + (f", export of {args.export_labels} labels" if args.export_labels else "")
          + (f", {args.history_labels} older labels stored" if args.history_labels else ""))
    print(f"server: uvicorn, {processes}{'es' if processes[0] != '1' else ''} "
          f"({server_flavour()}{', probe' if args.probe or args.profile else ''}); "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, machine busy "
          f"{m.machine_busy:.0%}, CPU time stolen by the host {m.machine_steal:.0%}")
    print(f"{'':<14} {'p50 ms':>8} {'p90 ms':>8} {'p99 ms':>8} {'max ms':>8} {'count':>7}")
    print(_row("round trip", [rt for _, rt in tally.round_trips]))
    print(_row("next", tally.nexts))
    print(_row("submit", tally.submits))
    if tally.export:
        during = [rt for t, rt in tally.round_trips
                  if tally.export["start"] - rt <= t <= tally.export["end"]]
        print(_row("  in export", during))
    for name, values in sorted(tally.pages.items()):
        print(_row(f"page {name}", values))
    for name, values in sorted(m.worker_timings.items()):
        print(_row(f"worker {name.split('_')[0] if name != 'labels_for_queries' else 'read'}",
                   values))
    rate = len(tally.label_ids) / m.seconds
    conflicts = tally.statuses["next 409"] + tally.statuses["submit 409"]
    print(f"{rate:.0f} labels/s ({len(tally.label_ids)} in {m.seconds:.1f} s); "
          f"204s: {tally.statuses['next 204']}, 409s: {conflicts}, "
          f"other errors: {len(tally.errors) - conflicts}")
    database = ("" if m.database_cpu_s is None else
                f", PostgreSQL {1000 * m.database_cpu_s / n:.2f} ms")
    print(f"CPU per round trip: server {1000 * m.server_cpu_s / n:.2f} ms "
          f"({m.server_cpu_s / m.seconds:.0%} of a core){database}, worker process "
          f"{1000 * m.worker_cpu_s / n:.2f} ms, client {1000 * m.client_cpu_s / n:.2f} ms "
          f"({m.client_cpu_s / m.seconds:.0%}); dashboards and export included")
    if tally.export:
        e = tally.export
        print(f"export: {e['bytes'] / 2**20:.0f} MiB of JSONL (status {e['status']:.0f}) in "
              f"{e['end'] - e['start']:.1f} s; server memory {e['rss_before_mib']:.0f} MiB "
              f"before, {e['rss_peak_mib']:.0f} MiB at most during it")
    p99 = 1000 * percentile(sorted(rt for _, rt in tally.round_trips), 0.99)
    print(f"target: p99 <= {TARGET_P99_MS:g} ms -> {'met' if p99 <= TARGET_P99_MS else 'missed'}")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--labellers", type=int, default=50)
    parser.add_argument("--queries", type=int, default=3000, help="timed round's queries")
    parser.add_argument("--warmup", type=int, default=250, help="warm-up round's queries")
    parser.add_argument("--think-ms", type=float, default=0.0,
                        help="mean pause between next and submit (exponential); 0: none")
    parser.add_argument("--poll-ms", type=float, default=2000.0,
                        help="wait after a 204 (nothing free: others hold the last leases); "
                        "the label page's POLL_MS")
    parser.add_argument("--database", choices=("sqlite", "postgres"), default="sqlite",
                        help="postgres: a fresh database beside SEPOA_TEST_POSTGRES_URL's")
    parser.add_argument("--workers", type=int, default=None,
                        help="uvicorn worker processes (default: 1 on SQLite, 2 on PostgreSQL)")
    parser.add_argument("--pollers", type=int, default=5,
                        help="dashboard pages polling the run page's endpoints every 5 s")
    parser.add_argument("--worker", action=argparse.BooleanOptionalAction, default=True,
                        help="a worker process pushes the timed queries in rounds and "
                        "heartbeats (--no-worker: all pushed before the timed round)")
    parser.add_argument("--round-size", type=int, default=100, help="the worker's round size")
    parser.add_argument("--eval-every-s", type=float, default=30.0,
                        help="the worker writes an eval row this often (the pages then redraw "
                        "the curves figure)")
    parser.add_argument("--export-labels", type=int, default=0,
                        help="seed this many labels of an older run and export every label "
                        "over HTTP during the timed round")
    parser.add_argument("--history-labels", type=int, default=0,
                        help="seed this many labels of an older run first, as a server that "
                        "has been labelling for a while holds (no export)")
    parser.add_argument("--labels-per-query", type=int, default=1,
                        help="distinct labellers' answers each query wants (a run's "
                        "feedback.labels_per_query); the rounds take that many labels per query")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds per round, at most")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--probe", action="store_true",
                        help="serve through the probe (timers on requests, lock waits, SQL)")
    parser.add_argument("--profile", action="store_true",
                        help="serve through the probe with cProfile on every server thread")
    parser.add_argument("--profile-top", type=int, default=25)
    parser.add_argument("--profile-out", type=Path,
                        help="keep the merged cProfile stats in this file (pstats format)")
    for hidden in ("--serve-probe", "--serve-worker"):
        parser.add_argument(hidden, action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--stats-file", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--url", help=argparse.SUPPRESS)
    parser.add_argument("--run-id", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--clips-dir", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.workers is None:
        args.workers = 2 if args.database == "postgres" else 1
    return args


def main() -> int:
    args = parse_args()
    if args.serve_probe:
        serve_probe(args.port, args.stats_file, args.profile)
        return 0
    if args.serve_worker:
        serve_worker(args)
        return 0

    with tempfile.TemporaryDirectory(prefix="bench-label-api-") as tmp_name:
        tmp = Path(tmp_name)
        with fresh_database(args, tmp) as url:
            m = run_rounds(args, tmp, url)
            report(args, m)
            if args.probe or args.profile:
                print_probe(tmp / "probe.json", len(m.tally.round_trips), args.profile_top)
                if args.profile_out and (tmp / "probe.prof").exists():
                    shutil.copyfile(tmp / "probe.prof", args.profile_out)
            answered = m.warm_label_ids + m.tally.label_ids
            problems = verify(url, m.run_id, answered, args.warmup + args.queries,
                              args.labels_per_query)
        problems += [f"request failed: {error}" for error in m.tally.errors[:20]]
        k = args.labels_per_query
        if len(m.warm_label_ids) != args.warmup * k or len(m.tally.label_ids) != args.queries * k:
            problems.append(f"rounds took {len(m.warm_label_ids)} of {args.warmup * k} and "
                            f"{len(m.tally.label_ids)} of {args.queries * k} labels")
        if args.export_labels and m.tally.export.get("status") != 200:
            problems.append(f"the export answered {m.tally.export.get('status')}")
    if problems:
        print(f"FAILED: {len(problems)} problems with the labels:", file=sys.stderr)
        for problem in problems[:30]:
            print(f"  {problem}", file=sys.stderr)
        return 1
    queries = args.warmup + args.queries
    print(f"verified in the database: {queries} queries with exactly {k} label(s) each, by "
          f"{k} different labellers, every 201's label stored, labels_used {len(answered)}, "
          "none left leased or pending: no duplicated or lost labels")
    return 0


if __name__ == "__main__":
    sys.exit(main())

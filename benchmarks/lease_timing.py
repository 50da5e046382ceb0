"""Whether a gold lease can be told from an ordinary one by its time, over loopback.

A real server (uvicorn on a free port, a fresh SQLite queue database, the lease rate limit
lifted) holds a human-taught run with gold pairs among ordinary ones. Labellers join until one
holds a gold pair and another an ordinary one; then each re-leases its pair (`GET
/api/label/next`: a reload renews the lease and returns the same pair) in turns, gold and
ordinary alternating, `--n` times each over one keep-alive connection per labeller. Prints the
median wall time of each kind, and the gap (gold minus ordinary) with a bootstrap 95% interval
of the difference of medians.

    .venv/bin/python benchmarks/lease_timing.py
    .venv/bin/python benchmarks/lease_timing.py --n 5000 --rounds 3
"""

from __future__ import annotations

import argparse
import os
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from labelqueue import claim_run, make_engine, push_queries, session_factory, set_clips  # noqa: E402
from labelqueue.models import Query  # noqa: E402

TOKEN = "lease-timing-operator-token-0123"
SECRET = "lease-timing-secret-key-0123456789"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def start_server(data: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = free_port()
    env = os.environ | {
        "SEPOA_DATABASE_URL": f"sqlite:///{data / 'queue.db'}", "SEPOA_DATA_DIR": str(data),
        "SEPOA_OPERATOR_TOKEN": TOKEN, "SEPOA_SECRET_KEY": SECRET,
        "SEPOA_LEASE_PER_S": "100000", "SEPOA_LEASE_BURST": "100000",
    }
    server = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "--factory", "server.app:create_app", "--host",
         "127.0.0.1", "--port", str(port), "--log-level", "warning"], cwd=ROOT, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while True:
        try:
            if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                return server, url
        except httpx.TransportError:
            pass
        if server.poll() is not None or time.monotonic() > deadline:
            server.kill()
            raise SystemExit("the server did not start")
        time.sleep(0.1)


def spec(position: int, gold: bool) -> dict[str, object]:
    return {"round": 0, "position": position, "segment_length": 50,
            "first_trajectory": 2 * position, "first_start": 10,
            "second_trajectory": 2 * position + 1, "second_start": 20,
            "first_segment_return": 10.0 + position, "second_segment_return": 3.0,
            "first_trajectory_return": 100.0, "second_trajectory_return": 50.0,
            **({"gold": True} if gold else {})}


def study_run(url: str, data: Path, pairs: int) -> set[int]:
    """A claimed human-taught run with `pairs` rendered pairs, one in five gold; the gold ids."""
    operator = {"Authorization": f"Bearer {TOKEN}"}
    run = httpx.post(url + "/api/runs", headers=operator, timeout=30, json={
        "task": "dmc:cheetah_run", "algo": "pebble", "preset": "tiny", "budget": 1000,
        "config": {"feedback.gold_rate": 0.2}}).json()
    engine = make_engine(f"sqlite:///{data / 'queue.db'}")
    with session_factory(engine)() as session:
        claim_run(session, worker_id="lease-timing")
        specs = [spec(i, gold=i % 5 == 2) for i in range(pairs)]
        ids = push_queries(session, run_id=run["id"], queries=specs)
        for query_id in ids:
            set_clips(session, query_id=query_id, first_clip=f"q{query_id}-a.mp4",
                      second_clip=f"q{query_id}-b.mp4")
        gold = {q.id for q in session.query(Query).filter(Query.gold.is_(True))}
    engine.dispose()
    return gold


def holders(url: str, gold: set[int]) -> dict[bool, httpx.Client]:
    """A labeller holding a gold pair and one holding an ordinary pair, each with a client."""
    found: dict[bool, httpx.Client] = {}
    for n in range(200):
        made = httpx.post(url + "/api/labellers", json={"name": f"timed-{n}"}, timeout=30,
                          headers={"Authorization": f"Bearer {TOKEN}"}).json()
        client = httpx.Client(base_url=url, timeout=30,
                              headers={"Authorization": f"Bearer {made['token']}"})
        leased = client.get("/api/label/next")
        is_gold = leased.status_code == 200 and leased.json()["query_id"] in gold
        if leased.status_code == 200 and is_gold not in found:
            found[is_gold] = client
        else:
            client.close()
        if len(found) == 2:
            return found
    raise SystemExit("no labeller got a gold pair and another an ordinary one")


def median_gap(gold: list[float], plain: list[float], rng: random.Random,
               draws: int = 2000) -> tuple[float, float, float]:
    """Median(gold) - median(plain), with a percentile bootstrap 95% interval."""
    gaps = sorted(statistics.median(rng.choices(gold, k=len(gold)))
                  - statistics.median(rng.choices(plain, k=len(plain))) for _ in range(draws))
    return (statistics.median(gold) - statistics.median(plain),
            gaps[int(0.025 * draws)], gaps[int(0.975 * draws)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=2000, help="re-leases of each kind per round")
    parser.add_argument("--rounds", type=int, default=2, help="rounds, each on a fresh server")
    parser.add_argument("--pairs", type=int, default=50, help="pairs the run holds")
    args = parser.parse_args()
    rng = random.Random(0)
    print(f"{'round':>5} {'gold ms':>8} {'ordinary ms':>11} {'gap ms':>8} {'95% interval':>18}")
    for round_ in range(args.rounds):
        with tempfile.TemporaryDirectory(prefix="sepoa-lease-timing-") as folder:
            data = Path(folder) / "data"
            server, url = start_server(data)
            try:
                gold_ids = study_run(url, data, args.pairs)
                clients = holders(url, gold_ids)
                times: dict[bool, list[float]] = {True: [], False: []}
                shown = {kind: client.get("/api/label/next").json()["query_id"]
                         for kind, client in clients.items()}
                for _ in range(50):  # warm up both paths
                    for client in clients.values():
                        client.get("/api/label/next")
                for i in range(args.n):
                    for kind in ((True, False) if i % 2 else (False, True)):
                        started = time.perf_counter()
                        answer = clients[kind].get("/api/label/next")
                        times[kind].append((time.perf_counter() - started) * 1000)
                        assert answer.json()["query_id"] == shown[kind]  # the same pair
                gap, low, high = median_gap(times[True], times[False], rng)
                print(f"{round_:>5} {statistics.median(times[True]):>8.3f} "
                      f"{statistics.median(times[False]):>11.3f} {gap:>+8.3f} "
                      f"[{low:+.3f}, {high:+.3f}]")
                for client in clients.values():
                    client.close()
            finally:
                server.terminate()
                server.wait(timeout=10)


if __name__ == "__main__":
    main()

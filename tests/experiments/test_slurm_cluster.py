"""`sepoa experiment slurm` on a real Slurm: a one-node cluster (munged, slurmctld, slurmd with a
throwaway configuration, tests/slurm_cluster.py) runs the printed script, as printed, for a
2-run grid; one array task is cancelled mid-run (`scancel`: SIGTERM), and every run still
finishes once, with nothing trained, asked or answered twice, and the queue's password in no
script, log or process list.

The queue is PostgreSQL when scripts/with_postgres.sh provides one (SEPOA_TEST_POSTGRES_URL,
given a password here that the throwaway server does not check), else a SQLite file with every
task pinned to the one node (`--node`). Skipped, saying why, where Slurm cannot be started.
"""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from slurm_cluster import NODE, Cluster, SlurmUnavailable
from sqlalchemy import create_engine, func, make_url, select

from labelqueue import Label, Query, Run, RunStatus, make_engine, session_factory

POSTGRES_URL = os.environ.get("SEPOA_TEST_POSTGRES_URL")
SEPOA = Path(sys.executable).parent / "sepoa"
STEPS = 1600  # three rounds of 10 pairs (tiny preset: budget 30, a round every 400 steps)
SPEC = f"""
name = "slurm-tiny"
preset = "tiny"
steps = {STEPS}
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]

[overrides]
"feedback.per_round" = 10
update_every = 4

[variants.PEBBLE]
algo = "pebble"
"""


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[Cluster]:
    started = Cluster(Path(f"/tmp/sepoa-slurm-{uuid.uuid4().hex[:8]}"))
    try:
        started.start()
    except SlurmUnavailable as err:
        started.stop()
        pytest.skip(f"no Slurm cluster could be started here: {err}")
    try:
        yield started
    finally:
        started.stop()
        shutil.rmtree(started.folder, ignore_errors=True)


@pytest.fixture
def queue(tmp_path: Path) -> Iterator[tuple[str, str]]:
    """(the queue's URL, its secret or "" for SQLite)."""
    if POSTGRES_URL is None:
        yield f"sqlite:///{tmp_path / 'queue.db'}", ""
        return
    schema = f"slurm_{uuid.uuid4().hex[:12]}"
    admin = create_engine(POSTGRES_URL)
    with admin.begin() as connection:
        connection.exec_driver_sql(f'CREATE SCHEMA "{schema}"')
    secret = f"pw-{uuid.uuid4().hex}"
    url = (make_url(POSTGRES_URL).set(password=secret)
           .update_query_dict({"options": f"-csearch_path={schema}"}))
    try:
        yield url.render_as_string(hide_password=False), secret
    finally:
        with admin.begin() as connection:
            connection.exec_driver_sql(f'DROP SCHEMA "{schema}" CASCADE')
        admin.dispose()


def wait_for(check: Callable[[], bool], timeout: float, what: str, cluster: Cluster) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}{cluster.logs()}")
        time.sleep(0.3)


def test_the_printed_script_trains_the_grid_and_survives_a_cancelled_task(
        tmp_path: Path, cluster: Cluster, queue: tuple[str, str]) -> None:
    started = time.monotonic()
    url, secret = queue
    results = tmp_path / "results"
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    env = {k: v for k, v in os.environ.items()
           if k not in ("SEPOA_DATABASE_URL", "SEPOA_DATABASE_URL_FILE")}
    env["MUJOCO_GL"] = env.get("MUJOCO_GL", "egl")
    with_url = env | {"SEPOA_DATABASE_URL": url}
    pinned = [] if secret else ["--node", NODE]

    enqueued = subprocess.run([str(SEPOA), "experiment", "run", str(spec), "--no-workers",
                               "--results", str(results)], env=with_url, capture_output=True,
                              text=True, timeout=60)
    assert enqueued.returncode == 0, enqueued.stderr
    assert "2 enqueued" in enqueued.stdout
    printed = subprocess.run([str(SEPOA), "experiment", "slurm", str(spec), "--workers", "2",
                              "--results", str(results), *pinned], env=with_url,
                             capture_output=True, text=True, timeout=60)
    assert printed.returncode == 0, printed.stderr
    script = tmp_path / "workers.sbatch"
    script.write_text(printed.stdout)
    assert f"exec {SEPOA} worker" in printed.stdout  # this sepoa, by absolute path
    assert "#SBATCH --mem=2G" in printed.stdout and "--open-mode=append" in printed.stdout

    # Submitted as printed, from a shell that holds no database URL at all.
    job = cluster.sbatch(script, env=env)
    engine = make_engine(url)
    sessions = session_factory(engine)

    def runs() -> dict[str, Run]:
        with sessions() as session:
            rows = session.scalars(select(Run).execution_options(populate_existing=True)).all()
            session.expunge_all()
        return {str(r.grid_key): r for r in rows}

    second = f"slurm-{job}-1"
    checkpoints = {key: results / key / "checkpoint.pt" for key in runs()}
    processes: list[str] = []

    def second_task_checkpointed() -> bool:
        processes.append(subprocess.run(["ps", "-eww", "-o", "args"], capture_output=True,
                                        text=True).stdout)
        held = [key for key, run in runs().items() if run.worker_id == second]
        return bool(held) and checkpoints[held[0]].exists()

    wait_for(second_task_checkpointed, 90, "task 1's first checkpoint", cluster)
    (key,) = [key for key, run in runs().items() if run.worker_id == second]
    other = next(k for k in checkpoints if k != key)
    assert runs()[other].status is RunStatus.RUNNING, "both tasks train side by side"
    assert any(f"{SEPOA} worker" in text for text in processes)

    # scancel: the task's worker checkpoints at its episode's end (or, inside a round, saves
    # the round's reward training after the current epoch) and releases the run, which task 0
    # takes over once its own run is done (not after the 300 s heartbeat timeout).
    cluster.run("scancel", f"{job}_1")
    cancelled = time.monotonic()
    wait_for(lambda: runs()[key].worker_id != second, 20, "the cancelled task's release",
             cluster)
    released_in = time.monotonic() - cancelled
    wait_for(lambda: not cluster.jobs(job), 150, "the array to end", cluster)

    logs = {path.name: path.read_text() for path in results.glob("slurm-*.log")}
    first_log, second_log = logs[f"slurm-{job}_0.log"], logs[f"slurm-{job}_1.log"]
    assert re.search(r"SIGTERM (inside the round )?at step", second_log), second_log
    assert re.search(r"released; the next worker resumes it( there)? \(now queued\)",
                     second_log), second_log
    final = runs()
    assert {k: r.status for k, r in final.items()} == {k: RunStatus.FINISHED for k in final}
    assert final[key].worker_id == f"slurm-{job}-0"  # taken over by the surviving task
    assert f"run {final[key].id}: resuming" in first_log

    with sessions() as session:
        for grid_key, run in final.items():
            folder = results / grid_key
            assert json.loads((folder / "done.json").read_text())["step"] == STEPS
            steps = [int(row["step"]) for row in csv.DictReader(
                (folder / "episodes.csv").open())]
            assert steps == sorted(set(steps)) and steps[-1] == STEPS, grid_key
            # Three rounds of 10 pairs, each answered once: no query or label twice.
            queries = session.scalars(select(Query).where(Query.run_id == run.id)).all()
            places = [(q.round, q.position) for q in queries]
            assert len(places) == len(set(places)) == 30, grid_key
            per_query = session.execute(
                select(Label.query_id, func.count()).join(Query, Query.id == Label.query_id)
                .where(Query.run_id == run.id).group_by(Label.query_id)).all()
            assert sorted(n for _, n in per_query) == [1] * 30, grid_key
            logged = [json.loads(line)["query_id"] for line in
                      (folder / "labels.jsonl").read_text().splitlines()]
            assert len(logged) == len(set(logged)) == 30, grid_key
    engine.dispose()

    if secret:  # the password: in none of the script, the logs or the process list
        assert secret not in printed.stdout + printed.stderr + enqueued.stdout
        assert not [name for name, text in logs.items() if secret in text]
        assert not [text for text in processes if secret in text]
        assert "postgresql+psycopg://sepoa:***@" in first_log
    status = subprocess.run([str(SEPOA), "experiment", "status", str(spec), "--results",
                             str(results)], env=with_url, capture_output=True, text=True,
                            timeout=60)
    assert "slurm-tiny: 2 runs: 2 finished" in status.stdout, status.stdout + status.stderr
    print(f"released {released_in:.1f} s after scancel; {time.monotonic() - started:.0f} s")

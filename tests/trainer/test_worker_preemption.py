"""A worker told to go (SIGTERM: kill, scancel, preemption; SIGUSR1: Slurm's warning before the
time limit) checkpoints at its episode's end and releases its run at once, so another worker
resumes it from there and ends with what an uninterrupted run learns; a worker that finds a
run held by a worker gone silent says so, and when the run is free, and waits to take it."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import update
from worker_helpers import (
    RUN,
    database,
    decisions,
    run_row,
    standalone_run,
    wait_for,
    worker_config,
)

from labelqueue import DEAD_WORKER_AFTER_S, Run, RunStatus, claim_run, create_run
from labelqueue.models import utcnow
from trainer.worker import run_worker

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return standalone_run(tmp_path_factory.mktemp("reference") / "run")


def test_a_signalled_worker_checkpoints_and_releases_its_run_for_the_next_worker(
        tmp_path: Path, reference: Path) -> None:
    sig = signal.SIGTERM
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="preempted", teacher="scripted", **RUN)
    data = tmp_path / "data"
    command = [sys.executable, "-m", "sepoa", "worker", "--database-url", url,
               "--data-dir", str(data), "--worker-id", "w1", "--once", "--poll-seconds", "0.1",
               "--threads", "1"]
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    worker = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    episodes = data / "runs" / f"run-{run.id}" / "episodes.csv"
    try:
        # The episodes file, not the heartbeat (every 2 s): on an idle host a tiny run can
        # reach its end between two heartbeats, and the signal must come mid-run.
        wait_for(lambda: episodes.exists() and len(episodes.read_text().splitlines()) >= 2,
                 what="the first episode's end")
        worker.send_signal(sig)
        _, err = worker.communicate(timeout=60)
    finally:
        if worker.poll() is None:
            worker.kill()
    assert worker.returncode == 0, err
    assert f"run {run.id}: {sig.name} at step" in err
    assert f"run {run.id}: {sig.name}: checkpointed at step" in err
    assert "released; the next worker resumes it (now queued)" in err

    released = run_row(sessions, run.id)
    assert released.status is RunStatus.QUEUED and released.worker_id is None
    assert released.step % 200 == 0 and 200 <= released.step < 1000  # an episode's end
    run_dir = data / "runs" / f"run-{run.id}"
    assert (run_dir / "checkpoint.pt").exists()

    # Another worker takes it at once (no heartbeat timeout) and resumes it.
    assert run_worker(worker_config(url, data, worker_id="w2")) == 1
    finished = run_row(sessions, run.id)
    assert (finished.status, finished.worker_id) == (RunStatus.FINISHED, "w2")
    steps = [int(row["step"]) for row in csv.DictReader((run_dir / "episodes.csv").open())]
    assert steps == sorted(set(steps)) and steps[-1] == 1000
    assert decisions(run_dir) == decisions(reference)  # nothing lost or used twice


def test_slurms_warning_before_the_time_limit_ends_an_idle_worker_cleanly(
        tmp_path: Path) -> None:
    """SIGUSR1 (`--signal=B:USR1@...`) is a departure like SIGTERM, not a crash (its default
    action would kill the worker with no word)."""
    url, _ = database(tmp_path)
    command = [sys.executable, "-m", "sepoa", "worker", "--database-url", url,
               "--data-dir", str(tmp_path / "data"), "--worker-id", "idle", "--poll-seconds",
               "0.1", "--threads", "1"]
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    worker = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert worker.stderr is not None
        for line in worker.stderr:
            if "waiting for runs in" in line:
                break
        worker.send_signal(signal.SIGUSR1)
        _, err = worker.communicate(timeout=30)
    finally:
        if worker.poll() is None:
            worker.kill()
    assert worker.returncode == 0
    assert "[worker idle] SIGUSR1: exiting" in err


def test_a_worker_says_which_run_a_silent_worker_holds_and_takes_it_when_it_is_free(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="held", teacher="scripted",
                         **RUN | {"config": RUN["config"] | {"steps": 400}})
        assert claim_run(session, worker_id="gone") is not None
        session.execute(update(Run).where(Run.id == run.id).values(
            heartbeat_at=utcnow() - timedelta(seconds=DEAD_WORKER_AFTER_S - 3)))
        session.commit()

    # With nothing else to do, a --once worker waits for the run rather than exit.
    assert run_worker(worker_config(url, tmp_path / "data", worker_id="w2")) == 1
    err = capsys.readouterr().err
    assert (f"run {run.id} (held) is held by worker gone, silent for 297 s (stopped or dead?); "
            "it can be taken over at ") in err
    assert " UTC, in 3 s, unless that worker comes back: waiting for it" in err
    assert f"run {run.id}: starting dmc:cheetah_run pebble" in err
    finished = run_row(sessions, run.id)
    assert (finished.status, finished.worker_id) == (RunStatus.FINISHED, "w2")

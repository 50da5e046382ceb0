"""A worker told to go (SIGTERM: kill, scancel, preemption; SIGUSR1: Slurm's warning before the
time limit) checkpoints at its episode's end, or inside a round saves the round's reward
training after the current epoch, and releases its run at once, so another worker resumes it
from there and ends with what an uninterrupted run learns; a worker that finds a run held by a
worker gone silent says so, and when the run is free, and waits to take it."""

from __future__ import annotations

import csv
import os
import re
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
    round_accuracies,
    run_row,
    standalone_run,
    wait_for,
    worker_config,
)

from labelqueue import DEAD_WORKER_AFTER_S, Run, RunStatus, claim_run, create_run
from labelqueue.models import utcnow
from runvocab.config import build_config
from trainer.checkpoint import load_checkpoint
from trainer.loop import TrainingRun
from trainer.queue_hooks import QueueHooks
from trainer.round_progress import ROUND_PROGRESS
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
    # At an episode's end, or, told inside a round's reward training, after its current epoch
    # (the test that follows takes that path on purpose).
    assert re.search(rf"run {run.id}: {sig.name} (inside the round )?at step", err), err
    assert re.search(rf"run {run.id}: {sig.name}: (checkpointed at step \d+|the round at step "
                     r"\d+ saved at reward epoch \d+) and released; the next worker resumes it"
                     r"( there)? \(now queued\)", err), err

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


def test_a_worker_told_to_go_inside_a_round_saves_its_reward_training_and_releases_the_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A late round trains for most of an hour on a busy core: longer than Slurm's warning or
    the launcher's grace. Told to go in it, the worker leaves after the current reward epoch
    with that training saved, and the next worker trains only the epochs left."""
    epochs = 6
    config = RUN["config"] | {"reward.max_epochs": epochs, "reward.stop_accuracy": 1.0}
    reference = tmp_path / "reference"
    TrainingRun(build_config(RUN["task"], RUN["preset"], {
        "algo": RUN["algo"], "seed": RUN["seed"], "feedback.budget": RUN["budget"],
        "teacher.eps": RUN["teacher_params"]["eps"], **config, "run_dir": str(reference)}),
        progress=False).train()

    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="preempted in a round", teacher="scripted",
                         **RUN | {"config": config})
    heard: list[int] = []
    reward_epoch = QueueHooks.reward_epoch

    def told_to_go_in_the_second_round(self: QueueHooks, step: int) -> bool:
        heard.append(step)
        if step >= 800 and heard.count(step) == 2:  # the second round's second epoch
            self.departure.signum = signal.SIGTERM
        return reward_epoch(self, step)

    monkeypatch.setattr(QueueHooks, "reward_epoch", told_to_go_in_the_second_round)
    data = tmp_path / "data"
    assert run_worker(worker_config(url, data, worker_id="w1")) == 1
    err = capsys.readouterr().err
    round_step = heard[-1]
    assert f"run {run.id}: SIGTERM inside the round at step {round_step}" in err
    assert (f"run {run.id}: SIGTERM: the round at step {round_step} saved at reward epoch 2 "
            "and released; the next worker resumes it there (now queued)") in err
    released = run_row(sessions, run.id)
    assert released.status is RunStatus.QUEUED and released.worker_id is None
    run_dir = data / "runs" / f"run-{run.id}"
    saved = load_checkpoint(str(run_dir / ROUND_PROGRESS))["state"]["training"]
    assert (saved["epochs"], saved["finished"]) == (2, False)
    assert load_checkpoint(str(run_dir / "checkpoint.pt"))["feedback"]["pending"]  # as opened

    heard.clear()
    monkeypatch.setattr(QueueHooks, "reward_epoch", lambda self, step: (
        heard.append(step), reward_epoch(self, step))[1])
    assert run_worker(worker_config(url, data, worker_id="w2")) == 1
    assert run_row(sessions, run.id).status is RunStatus.FINISHED
    assert heard.count(round_step) == epochs - 2  # only the epochs the round had left
    assert not (run_dir / ROUND_PROGRESS).exists()
    assert decisions(run_dir) == decisions(reference)
    assert round_accuracies(run_dir) == round_accuracies(reference)


def test_a_worker_told_to_go_while_pretraining_saves_the_pretrainings_progress(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """An S-EPOA run's skill pretraining can take hours. Told to go in it, the worker leaves at
    the end of the episode with the pretraining's progress saved and releases the run; the
    next worker pretrains on from there."""
    config = {"steps": 200, "threads": 1, "skill.pretrain_steps": 700,
              "checkpoint_every": 100_000}  # no periodic checkpoint within the pretraining
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="preempted while pretraining", teacher="scripted",
                         **RUN | {"algo": "sepoa", "config": config})
    pretraining = QueueHooks.pretraining

    def told_to_go_at_250(self: QueueHooks, step: int) -> bool:
        if step == 250:
            self.departure.signum = signal.SIGTERM
        return pretraining(self, step)

    monkeypatch.setattr(QueueHooks, "pretraining", told_to_go_at_250)
    data = tmp_path / "data"
    assert run_worker(worker_config(url, data, worker_id="w1")) == 1
    err = capsys.readouterr().err
    assert (f"run {run.id}: SIGTERM while pretraining the skill snapshot: leaving at the end of "
            "this episode with the pretraining's progress saved, then releasing the run") in err
    assert re.search(rf"run {run.id}: SIGTERM: pretraining left at step 400 of 700, its "
                     r"progress saved in \S+\.pt\.partial; released, and the next worker goes "
                     r"on from there \(now queued\)", err), err
    released = run_row(sessions, run.id)
    assert released.status is RunStatus.QUEUED and released.worker_id is None
    [partial] = (data / "snapshots").glob("*.pt.partial")

    monkeypatch.setattr(QueueHooks, "pretraining", pretraining)
    assert run_worker(worker_config(url, data, worker_id="w2")) == 1
    assert "pretraining goes on from step 400 of 700" in capsys.readouterr().err
    assert run_row(sessions, run.id).status is RunStatus.FINISHED
    assert not partial.exists() and partial.with_suffix("").exists()


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
    lines = []
    try:
        assert worker.stderr is not None
        for line in worker.stderr:
            lines.append(line)
            if "waiting for runs in" in line:
                break
        worker.send_signal(signal.SIGUSR1)
        _, err = worker.communicate(timeout=30)
    finally:
        if worker.poll() is None:
            worker.kill()
    assert worker.returncode == 0
    assert "[worker idle] SIGUSR1: exiting" in err
    # Every line names the worker: the rendering check's and the threads' too.
    lines += err.splitlines(keepends=True)
    assert len(lines) >= 4 and all(line.startswith("[worker idle] ") for line in lines), lines


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


def test_a_worker_with_nothing_to_claim_names_the_runs_others_hold_as_it_exits(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A task resubmitted right after a kill -9: its run's worker looks alive for a minute."""
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="held", teacher="scripted", **RUN)
        assert claim_run(session, worker_id="killed") is not None
        session.execute(update(Run).where(Run.id == run.id).values(
            heartbeat_at=utcnow() - timedelta(seconds=20)))
        session.commit()
    assert run_worker(worker_config(url, tmp_path / "data", worker_id="w2")) == 0
    err = capsys.readouterr().err
    assert re.search(
        rf"\[worker w2\] no run left to claim: exiting; run {run.id} \(held\) is held by "
        r"worker killed, last heartbeat 2\d s ago \(if that worker is dead, a worker started "
        r"after \d\d:\d\d:\d\d UTC, in 2[78]\d s, takes it over\)\n", err), err

"""A worker whose run needs a skill snapshot another worker is pretraining does not wait idle
for it while other runs are queued: it sets the run aside (queued again, untouched) and trains
another, then comes back to it."""

from __future__ import annotations

import fcntl
import threading
from pathlib import Path

import pytest
from worker_helpers import RUN, database, run_row, wait_for, worker_config

from labelqueue import RunStatus, create_run
from runvocab.snapshot_names import snapshot_path
from trainer.worker import run_config, run_worker


def test_a_run_waiting_for_another_workers_snapshot_is_set_aside_for_a_queued_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        needs_snapshot = create_run(session, name="needs the snapshot", teacher="scripted",
                                    **RUN | {"algo": "sepoa", "config": {
                                        "steps": 200, "threads": 1, "skill.pretrain_steps": 700}})
        other = create_run(session, name="needs none", teacher="scripted",
                           **RUN | {"algo": "sac", "config": {"steps": 200, "threads": 1}})
    worker = worker_config(url, tmp_path / "data", worker_id="w1")
    snapshot = snapshot_path(run_config(needs_snapshot, worker))
    Path(snapshot).parent.mkdir(parents=True)
    # Another worker's pretraining holds the snapshot's lock until the other run has finished.
    lock = open(f"{snapshot}.lock", "a")  # noqa: SIM115
    fcntl.flock(lock, fcntl.LOCK_EX)

    def pretrained_elsewhere() -> None:
        try:
            wait_for(lambda: run_row(sessions, other.id).status is RunStatus.FINISHED,
                     timeout=300, what="the run that needs no snapshot to finish")
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
            lock.close()

    holder = threading.Thread(target=pretrained_elsewhere, daemon=True)
    holder.start()
    assert run_worker(worker) == 2
    holder.join(timeout=10)

    err = capsys.readouterr().err
    assert (f"run {needs_snapshot.id}: another worker is pretraining its skill snapshot; set "
            "aside, to train another run meanwhile (now queued)") in err
    first, second = run_row(sessions, other.id), run_row(sessions, needs_snapshot.id)
    assert first.status is second.status is RunStatus.FINISHED
    assert first.finished_at is not None and second.finished_at is not None
    assert first.finished_at < second.finished_at
    assert Path(snapshot).exists()  # the lock came free, and the worker pretrained it itself

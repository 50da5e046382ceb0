"""A worker whose run needs a skill snapshot another worker is pretraining does not wait idle
for it while other runs are queued: it sets the run aside (queued again, untouched) and trains
another, then comes back to it. With nothing else to claim, or a database that does not answer
the check, it waits for the snapshot."""

from __future__ import annotations

import fcntl
import threading
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.exc import OperationalError
from worker_helpers import RUN, database, run_row, worker_config

from labelqueue import Run, RunStatus, claim_run, create_run
from runvocab.snapshot_names import snapshot_path
from trainer import queue_hooks
from trainer import worker as worker_module
from trainer.queue_hooks import QueueHooks, SnapshotBusy
from trainer.worker import run_config, run_worker

SEPOA = RUN | {"algo": "sepoa", "config": {"steps": 200, "threads": 1,
                                           "skill.pretrain_steps": 700}}


def hold_lock_until(snapshot: str, free: threading.Event) -> threading.Thread:
    """Another worker's pretraining: the snapshot's lock, held until `free` is set."""
    Path(snapshot).parent.mkdir(parents=True, exist_ok=True)
    lock = open(f"{snapshot}.lock", "a")  # noqa: SIM115
    fcntl.flock(lock, fcntl.LOCK_EX)

    def hold() -> None:
        free.wait(timeout=300)
        fcntl.flock(lock, fcntl.LOCK_UN)
        lock.close()

    holder = threading.Thread(target=hold, daemon=True)
    holder.start()
    return holder


def test_a_run_waiting_for_another_workers_snapshot_is_set_aside_for_a_queued_one(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        needs_snapshot = create_run(session, name="needs the snapshot", teacher="scripted",
                                    **SEPOA)
        other = create_run(session, name="needs none", teacher="scripted",
                           **RUN | {"algo": "sac", "config": {"steps": 200, "threads": 1}})
    worker = worker_config(url, tmp_path / "data", worker_id="w1")
    cfg = run_config(needs_snapshot, worker)
    free = threading.Event()
    holder = hold_lock_until(snapshot_path(cfg), free)
    # What the run looked like when the worker moved on to the other one.
    seen: dict[str, Any] = {}
    train = worker_module.train_claimed_run

    def watching(sessions_: Any, run: Run, *args: Any) -> RunStatus | None:
        if run.id == other.id:
            seen["row"] = run_row(sessions, needs_snapshot.id)
            seen["folder"] = Path(cfg.run_dir).exists()
            free.set()  # the other worker's pretraining ends meanwhile
        return train(sessions_, run, *args)

    monkeypatch.setattr(worker_module, "train_claimed_run", watching)
    assert run_worker(worker) == 2
    holder.join(timeout=10)

    err = capsys.readouterr().err
    assert (f"run {needs_snapshot.id}: another worker is pretraining its skill snapshot; set "
            "aside, to train another run meanwhile (now queued)") in err
    aside = seen["row"]
    assert aside.status is RunStatus.QUEUED and aside.worker_id is None
    assert aside.started_at is None and not seen["folder"]  # as if never claimed
    first, second = run_row(sessions, other.id), run_row(sessions, needs_snapshot.id)
    assert first.status is second.status is RunStatus.FINISHED
    assert first.finished_at is not None and second.finished_at is not None
    assert first.finished_at < second.finished_at
    assert Path(snapshot_path(cfg)).exists()  # the lock came free: the worker pretrained it


def test_with_only_runs_of_the_busy_snapshot_left_a_worker_waits_for_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Two runs of one snapshot: the first is set aside for the second, which then waits (the
    run set aside is no reason to set the second aside), and both train once it is free."""
    url, sessions = database(tmp_path)
    with sessions() as session:
        first = create_run(session, name="first", teacher="scripted", **SEPOA)
        second = create_run(session, name="second", teacher="scripted", **SEPOA)
    worker = worker_config(url, tmp_path / "data", worker_id="w1")
    free = threading.Event()
    snapshot = snapshot_path(run_config(first, worker))
    assert snapshot == snapshot_path(run_config(second, worker))
    holder = hold_lock_until(snapshot, free)
    waiting = QueueHooks.waiting_for_snapshot

    def free_once_the_second_waits(self: QueueHooks) -> None:
        waiting(self)  # raises SnapshotBusy where the run is set aside
        if self.run_id == second.id:
            free.set()

    monkeypatch.setattr(QueueHooks, "waiting_for_snapshot", free_once_the_second_waits)
    assert run_worker(worker) == 2
    holder.join(timeout=10)

    err = capsys.readouterr().err
    assert err.count("set aside") == 1 and f"run {first.id}: another worker" in err
    assert run_row(sessions, first.id).status is RunStatus.FINISHED
    assert run_row(sessions, second.id).status is RunStatus.FINISHED


def test_a_worker_coming_back_to_a_run_it_set_aside_does_not_set_it_aside_again(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Runs A and C need the busy snapshot, B none. The worker sets A aside for C, C for B;
    another worker takes B first, so the worker comes back to A with C still set aside: C is no
    reason to set A aside again, and A waits for the snapshot."""
    url, sessions = database(tmp_path)
    with sessions() as session:
        a = create_run(session, name="A", teacher="scripted", **SEPOA)
        c = create_run(session, name="C", teacher="scripted", **SEPOA)
        b = create_run(session, name="B", teacher="scripted",
                       **RUN | {"algo": "sac", "config": {"steps": 200, "threads": 1}})
    worker = worker_config(url, tmp_path / "data", worker_id="w1")
    free = threading.Event()
    holder = hold_lock_until(snapshot_path(run_config(a, worker)), free)
    claim = worker_module.claim_run

    def another_worker_takes_b_first(session: Any, *, worker_id: str,
                                     skip: Any = ()) -> Run | None:
        if set(skip) == {a.id, c.id}:
            taken = claim(session, worker_id="w2", skip=skip)
            assert taken is not None and taken.id == b.id
        return claim(session, worker_id=worker_id, skip=skip)

    waiting = QueueHooks.waiting_for_snapshot

    def free_once_a_waits(self: QueueHooks) -> None:
        waiting(self)
        if self.run_id == a.id:
            free.set()

    monkeypatch.setattr(worker_module, "claim_run", another_worker_takes_b_first)
    monkeypatch.setattr(QueueHooks, "waiting_for_snapshot", free_once_a_waits)
    assert run_worker(worker) == 2
    holder.join(timeout=10)

    err = capsys.readouterr().err
    assert err.count(f"run {a.id}: another worker is pretraining") == 1, err
    assert err.count(f"run {c.id}: another worker is pretraining") == 1, err
    assert run_row(sessions, a.id).status is run_row(sessions, c.id).status \
        is RunStatus.FINISHED
    assert run_row(sessions, b.id).worker_id == "w2"


def test_a_database_error_in_the_set_aside_check_leaves_the_run_waiting_not_failed(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        created = create_run(session, name="waits", teacher="scripted", **SEPOA)
        run = claim_run(session, worker_id="w1")
    assert run is not None and run.id == created.id
    worker = worker_config(url, tmp_path / "data", worker_id="w1")
    hooks = QueueHooks(sessions, run, worker, run_config(run, worker), scripted_labeller_id=0)

    def unanswered(session: Any, **_: Any) -> bool:
        raise OperationalError("SELECT ...", {}, Exception("database is locked"))

    monkeypatch.setattr(queue_hooks, "other_claimable", unanswered)
    hooks.waiting_for_snapshot()  # no SnapshotBusy, no error: the run waits on
    assert "could not look for other queued runs (database is locked)" in capsys.readouterr().err
    assert run_row(sessions, run.id).status is RunStatus.RUNNING
    # The next check, 30 s on, asks again.
    monkeypatch.setattr(queue_hooks, "other_claimable", lambda session, **_: True)
    hooks.next_set_aside_check = 0.0
    with pytest.raises(SnapshotBusy):
        hooks.waiting_for_snapshot()

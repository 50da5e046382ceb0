"""The trainer worker: claims runs from the queue database, trains them, and hands them back.

    sepoa worker --database-url sqlite:///data/queue.db --data-dir data

A worker trains one run at a time; any number of workers may share one database. For each run
it claims (a queued one, or one whose worker stopped heartbeating), it takes the configuration
stored with the run when it was created (a run stored before that was kept: resolved from the
row's task, algorithm, preset, seed, budget, teacher parameters and config overrides), resumes
from the checkpoint in the run's folder if there is one, and trains with `QueueHooks`.
A run's folder is `<data dir>/runs/run-<id>`; an experiment's run (one with a grid key) goes to
`<results>/<grid key>`, i.e. `<results>/<spec name>/<run folder>`, with its skill snapshots in
`<results>/snapshots`, so every worker given the same (shared) results folder writes the grid
where `sepoa experiment status` and `sepoa report` read it. The worker marks the folder's end:
`done.json` (the run's summary), `stopped.json` (stopped by an operator; its summary) or
`failed.json` (the error). The hooks (`trainer.queue_hooks.QueueHooks`) heartbeat, obey the
operator, mirror metrics, and push each round's queries and take their answers from the queue.

A worker told to go (SIGTERM: `kill`, `scancel`, a scheduler's preemption, its launcher's stop;
SIGUSR1: the warning Slurm sends before the time limit with `--signal`) ends its run at the end
of the current episode, after a checkpoint (or, while the run pretrains its skill snapshot,
after saving the pretraining's progress), and releases it (`labelqueue.release_run`): the run
is queued again at once, and the next worker resumes it from that checkpoint without waiting
for the heartbeat timeout. Told inside a round's reward training, which can outlast the
warning, it leaves after the current reward epoch with that training saved
(`trainer/round_progress.py`), and the next worker goes on from that epoch. A second such
signal ends the worker at once. A worker with `once` that finds nothing to claim but a run held
by a worker that has gone silent says so, and when the run may be taken over, and waits for it
rather than exit.

A run whose skill snapshot another worker is pretraining (under the snapshot's file lock) is
set aside while any other run is claimable: released untouched, queued again, its folder
removed, and skipped by this worker's claims until it has trained another run; with nothing
else to claim, the worker takes it back and waits for the snapshot, heartbeating.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sys
import time
import traceback
from collections.abc import Collection
from datetime import timedelta
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    DEAD_WORKER_AFTER_S,
    Conflict,
    Run,
    RunStatus,
    claim_run,
    create_labeller,
    find_labeller,
    finish_run,
    heartbeat_age,
    make_engine,
    mask_url,
    migrate,
    read_run,
    release_run,
    session_factory,
    silent_holders,
)
from labelqueue.run_config import run_config as stored_run_config
from runvocab.config import RunConfig, apply_overrides
from runvocab.snapshot_names import shared_snapshot_dir
from trainer.dataset_labelling import DatasetLabelling
from trainer.departure import Departure, leave_on_signals
from trainer.loop import CHECKPOINT, TrainingRun
from trainer.queue_hooks import (
    SCRIPTED_LABELLER,
    Interrupted,
    LostRun,
    QueueHooks,
    SnapshotBusy,
)
from trainer.skills.pretrain import PretrainingLeft
from trainer.worker_config import WorkerConfig

DONE, FAILED, STOPPED = "done.json", "failed.json", "stopped.json"
"""a run folder's end, as the worker marks it"""



def run_config(run: Run, worker: WorkerConfig) -> RunConfig:
    """The config the run was stored with (`labelqueue.run_config`), in this worker's folders;
    ValueError naming a bad field of a run stored without one."""
    cfg = stored_run_config(run)
    if run.grid_key is not None:  # an experiment's run: in the shared results folder
        root, folder = worker.results_root, worker.results_root / run.grid_key
    else:
        root, folder = worker.data_dir, worker.data_dir / "runs" / f"run-{run.id}"
    local: dict[str, object] = {"run_dir": str(folder)}
    # S-EPOA's skill snapshots are shared by the runs of a folder (made on first use, once).
    local |= shared_snapshot_dir(run.config, root)
    if worker.device is not None:
        local["device"] = worker.device
    if worker.threads is not None:
        local["threads"] = worker.threads
    return apply_overrides(cfg, local)


def scripted_labeller_id(sessions: sessionmaker[Session]) -> int:
    """The labeller the scripted teacher answers as, created on first use."""
    with sessions() as session:
        labeller = find_labeller(session, name=SCRIPTED_LABELLER)
        if labeller is None:
            try:
                labeller, _token = create_labeller(session, name=SCRIPTED_LABELLER)
            except Conflict:  # another worker created it just now
                labeller = find_labeller(session, name=SCRIPTED_LABELLER)
        assert labeller is not None
        return labeller.id


def train_claimed_run(sessions: sessionmaker[Session], run: Run, worker: WorkerConfig,
                      scripted_id: int, departure: Departure | None = None,
                      set_aside: Collection[int] = ()) -> RunStatus | None:
    """Train a run this worker has claimed, and end it; its final status (None if lost). Told
    to go (`departure`), the worker releases the run after its checkpoint: queued again. A run
    whose skill snapshot another worker is pretraining, while runs other than it and those in
    `set_aside` are claimable, is released untouched (its folder removed, as never started)
    and SnapshotBusy raised, for the worker to claim another."""
    log = f"[worker {worker.worker_id}] run {run.id}"
    departure = departure or Departure()
    if departure.due:  # told to go as it claimed the run: hand it on untouched
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: released "
                        "before training")
    try:
        cfg = run_config(run, worker)
        resume = os.path.exists(os.path.join(cfg.run_dir, CHECKPOINT))
        if not resume and os.path.isdir(cfg.run_dir):
            shutil.rmtree(cfg.run_dir)  # an attempt that died before its first checkpoint
        for marker in (DONE, FAILED, STOPPED):
            Path(cfg.run_dir, marker).unlink(missing_ok=True)
        hooks = QueueHooks(sessions, run, worker, cfg, scripted_id, departure, set_aside)
        print(f"{log}: {'resuming' if resume else 'starting'} {run.task} {run.algo} "
              f"in {cfg.run_dir}", file=sys.stderr, flush=True)
        if run.dataset is not None:  # a labelling-only run over a dataset: no training
            labelling = DatasetLabelling(cfg, run.dataset, resume=resume, hooks=hooks,
                                         episode_store=hooks.episodes)
            summary = labelling.train()
        else:
            summary = TrainingRun(cfg, resume=resume, progress=False, hooks=hooks).train()
        hooks.beat(int(summary["step"]), force=True)  # the final step and progress, on record
    except LostRun as err:
        print(f"{log}: lost ({err})", file=sys.stderr, flush=True)
        return None
    except Interrupted as err:
        return _release(sessions, run.id, worker, f"{log}: {err}; released without a new "
                        "checkpoint")
    except SnapshotBusy as err:
        if not resume:  # a fresh run: as if never claimed, for the stop rule's started seeds
            shutil.rmtree(cfg.run_dir, ignore_errors=True)
        _release(sessions, run.id, worker, f"{log}: {err}; set aside, to train another run "
                 "meanwhile", untouched=not resume)
        raise
    except PretrainingLeft as err:
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: {err}; released, "
                        "and the next worker goes on from there")
    except Exception as err:  # noqa: BLE001 - any failure ends the run as failed, with why
        traceback.print_exc()
        error = f"{type(err).__name__}: {err}"
        if "cfg" in locals():
            _mark(cfg.run_dir, FAILED, {"reason": error})
        return _end(sessions, run.id, worker, RunStatus.FAILED, error)
    if departure.due and "round_epochs_saved" in summary:
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: the round at step "
                        f"{summary['step']} saved at reward epoch "
                        f"{summary['round_epochs_saved']:.0f} and released; the next worker "
                        "resumes it there")
    if departure.due and summary.get("stopped"):
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: checkpointed at "
                        f"step {summary['step']} and released; the next worker resumes it")
    status = RunStatus.STOPPED if summary.get("stopped") else RunStatus.FINISHED
    print(f"{log}: {status} at step {summary['step']}", file=sys.stderr, flush=True)
    _mark(cfg.run_dir, DONE if status is RunStatus.FINISHED else STOPPED, summary)
    return _end(sessions, run.id, worker, status, None)


def _mark(run_dir: str, name: str, data: dict[str, Any]) -> None:
    """`done.json` / `failed.json` / `stopped.json` in the run's folder, for reports that read
    folders only."""
    path = Path(run_dir, name)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data | {"at": time.strftime("%Y-%m-%d %H:%M:%S")},
                                  default=str) + "\n")
        os.replace(tmp, path)
    except OSError as err:
        print(f"cannot write {path}: {err}", file=sys.stderr, flush=True)


def _end(sessions: sessionmaker[Session], run_id: int, worker: WorkerConfig, status: RunStatus,
         error: str | None) -> RunStatus | None:
    with sessions() as session:
        try:
            return finish_run(session, run_id=run_id, worker_id=worker.worker_id,
                              status=status, error=error).status
        except Conflict:  # requeued or taken over meanwhile, or force-stopped: not ours to end
            return read_run(session, run_id=run_id).status


def _release(sessions: sessionmaker[Session], run_id: int, worker: WorkerConfig,
             message: str, untouched: bool = False) -> RunStatus | None:
    with sessions() as session:
        try:
            status = release_run(session, run_id=run_id, worker_id=worker.worker_id,
                                 untouched=untouched).status
        except Conflict:  # requeued or taken over meanwhile: not ours to release
            return read_run(session, run_id=run_id).status
    print(f"{message} (now {status})", file=sys.stderr, flush=True)
    return status


def _report_silent(sessions: sessionmaker[Session], worker: WorkerConfig,
                   told: set[tuple[int, str]]) -> bool:
    """Say which runs are held by workers gone silent, and when each may be taken over (once
    per run and holder); whether there are any."""
    with sessions() as session:
        held = silent_holders(session, worker_id=worker.worker_id)
    for run in held:
        if (run.id, str(run.worker_id)) in told or run.heartbeat_at is None:
            continue
        told.add((run.id, str(run.worker_id)))
        age = heartbeat_age(run) or 0.0
        free_at = run.heartbeat_at + timedelta(seconds=DEAD_WORKER_AFTER_S)
        left = max(0.0, DEAD_WORKER_AFTER_S - age)
        print(f"[worker {worker.worker_id}] run {run.id} ({run.grid_key or run.name}) is held "
              f"by worker {run.worker_id}, silent for {age:.0f} s (stopped or dead?); it can "
              f"be taken over at {free_at:%H:%M:%S} UTC, in {left:.0f} s, unless that worker "
              f"comes back{': waiting for it' if worker.once else ''}",
              file=sys.stderr, flush=True)
    return bool(held)


def _held_elsewhere(sessions: sessionmaker[Session], worker: WorkerConfig) -> str:
    """The runs other workers hold, each with its heartbeat's age and when any worker may take
    it over should its worker be dead (one killed a moment ago still looks alive), as the end
    of the exit line."""
    with sessions() as session:
        held = silent_holders(session, worker_id=worker.worker_id, silent_after=0.0)
    parts = []
    for run in held:
        if run.heartbeat_at is None:
            continue
        age = heartbeat_age(run) or 0.0
        free_at = run.heartbeat_at + timedelta(seconds=DEAD_WORKER_AFTER_S)
        parts.append(f"run {run.id} ({run.grid_key or run.name}) is held by worker "
                     f"{run.worker_id}, last heartbeat {age:.0f} s ago (if that worker is "
                     f"dead, a worker started after {free_at:%H:%M:%S} UTC, in "
                     f"{max(0.0, DEAD_WORKER_AFTER_S - age):.0f} s, takes it over)")
    return "; " + "; ".join(parts) if parts else ""


def run_worker(worker: WorkerConfig, departure: Departure | None = None) -> int:
    """Claim and train runs until interrupted (or, with `once`, until none is waiting and none
    is held by a worker gone silent). Told to go (SIGTERM, SIGUSR1), it checkpoints and releases
    its run, and returns."""
    for attempt in range(5):  # the server may be migrating the same database right now
        try:
            migrate(worker.database_url)
            break
        except Exception:  # noqa: BLE001
            if attempt == 4:
                raise
            time.sleep(1.0)
    departure = departure or Departure()
    previous = leave_on_signals(departure)
    engine = make_engine(worker.database_url)
    sessions = session_factory(engine)
    told: set[tuple[int, str]] = set()
    try:
        scripted_id = scripted_labeller_id(sessions)
        print(f"[worker {worker.worker_id}] waiting for runs in {mask_url(worker.database_url)}",
              file=sys.stderr, flush=True)
        trained = 0
        set_aside: set[int] = set()
        """runs released while another worker pretrains their snapshot; skipped by the next
        claims while anything else is claimable, forgotten once a run is trained"""
        while not departure.due:
            with sessions() as session:
                run = claim_run(session, worker_id=worker.worker_id, skip=set_aside)
                if run is None and set_aside:  # nothing else: wait for a snapshot after all
                    run = claim_run(session, worker_id=worker.worker_id)
            if run is None:
                if not _report_silent(sessions, worker, told) and worker.once:
                    print(f"[worker {worker.worker_id}] no run left to claim: exiting"
                          f"{_held_elsewhere(sessions, worker)}", file=sys.stderr, flush=True)
                    return trained
                time.sleep(worker.poll_seconds)
                continue
            try:
                train_claimed_run(sessions, run, worker, scripted_id, departure, set_aside)
            except SnapshotBusy:
                set_aside.add(run.id)
                continue
            set_aside.clear()
            trained += 1
        print(f"[worker {worker.worker_id}] {departure.name}: exiting", file=sys.stderr,
              flush=True)
        return trained
    finally:
        engine.dispose()
        for sig, handler in previous.items():
            signal.signal(sig, handler)

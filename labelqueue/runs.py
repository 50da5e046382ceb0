"""Runs: created by an operator, claimed and driven by a worker, steered by the operator.

    worker:    queued -> running (claim_run)
               running | paused | stopping -> finished | failed | stopped (finish_run)
    operator:  running <-> paused (pause, resume)
               running | paused -> stopping (stop; the worker checkpoints and ends as stopped)
               queued | stopping -> stopped (cancel; or a stop whose worker died)
               running | paused | stopping, no worker holds it -> stopped (stop_run)
               stopped | failed -> queued (requeue)

A worker that stops heartbeating loses its running run to the next worker that claims one; the
newcomer resumes from the run's last checkpoint. A worker told to go (SIGTERM, a scheduler's
preemption) checkpoints and gives its run back at once (release_run), so the next worker need
not wait for the heartbeat to age.
"""

from __future__ import annotations

import socket
from collections.abc import Collection, Mapping
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, and_, case, literal, or_, select, update
from sqlalchemy.orm import Session

from labelqueue.coerce import json_object
from labelqueue.errors import Conflict, Invalid, InvalidTransition
from labelqueue.instructions import checked_instruction, record_instruction
from labelqueue.models import Run, RunStatus, TeacherKind, UTCDateTime, Worker, utcnow
from labelqueue.run_config import resolve, with_teacher
from labelqueue.transaction import changed, detach, get_row, reading, transaction
from runvocab.clip_format import parse_clip_size

EXTERNAL = "external"
"""the `algo` of a run no worker trains (`externalruns`): never claimed"""
HOST = socket.gethostname()[:200]
"""this process's host, recorded on its worker row (`workers.host`)"""
DEAD_WORKER_AFTER_S = 300.0
"""a running run whose heartbeat is older than this may be claimed by another worker"""
SILENT_WORKER_AFTER_S = 60.0
"""a running run whose heartbeat is older than this has a worker that may be dead: a training
worker beats every few seconds (a long evaluation or reward-model fit can hold it longer)"""

# Which statuses an operator may move a run to, and from where.
OPERATOR_MOVES: dict[RunStatus, tuple[RunStatus, ...]] = {
    RunStatus.PAUSED: (RunStatus.RUNNING,),
    RunStatus.RUNNING: (RunStatus.PAUSED,),
    RunStatus.STOPPING: (RunStatus.RUNNING, RunStatus.PAUSED),
    # From stopping too: for when the worker died before it could acknowledge.
    RunStatus.STOPPED: (RunStatus.QUEUED, RunStatus.STOPPING),
    RunStatus.QUEUED: (RunStatus.STOPPED, RunStatus.FAILED),
}
EXTERNAL_MOVES: dict[RunStatus, tuple[RunStatus, ...]] = {
    RunStatus.PAUSED: (RunStatus.RUNNING,),
    RunStatus.RUNNING: (RunStatus.PAUSED, RunStatus.STOPPED),
    RunStatus.STOPPED: (RunStatus.RUNNING, RunStatus.PAUSED),
}
"""an external run's moves (no worker): a stop ends it at once, a requeue runs it again"""
WORKER_ENDS = (RunStatus.FINISHED, RunStatus.FAILED, RunStatus.STOPPED)
"""the statuses a worker may end its run with"""
OWNED = (RunStatus.RUNNING, RunStatus.PAUSED, RunStatus.STOPPING)
"""the statuses in which a run belongs to its worker"""
TEACHABLE = (RunStatus.QUEUED, RunStatus.RUNNING, RunStatus.PAUSED)
"""the statuses in which a run's teacher may change: a worker trains it, or will"""


def labels_per_query(run: Run) -> int:
    """Answers each of the run's queries takes (`feedback.labels_per_query`, 1 by default)."""
    if run.resolved_config is not None:
        return int(run.resolved_config["feedback"]["labels_per_query"])
    return int((run.config or {}).get("feedback.labels_per_query", 1))


def budget_spent(run: Run) -> bool:
    """The budget pays for no more queries: fewer answers are left than one query takes (the
    trainer stops asking there, possibly short of `budget`)."""
    return run.budget - run.labels_used < labels_per_query(run)

def checked_clip_size(clip_size: str | None) -> None:
    """Invalid for a clip size a run may not choose (`runvocab.clip_format.CLIP_SIZES`)."""
    if clip_size is not None:
        try:
            parse_clip_size(clip_size)
        except ValueError as err:
            raise Invalid(str(err)) from None


def create_run(
    session: Session,
    *,
    name: str,
    task: str,
    algo: str,
    budget: int,
    preset: str = "small",
    seed: int = 0,
    teacher: TeacherKind | str = TeacherKind.HUMAN,
    teacher_params: Mapping[str, Any] | None = None,
    config: Mapping[str, Any] | None = None,
    instruction: str | None = None,
    clip_size: str | None = None,
    grid_key: str | None = None,
    dataset: str | None = None,
) -> Run:
    """A queued run, for the next free worker to claim. `instruction`: the operator's text for
    labellers (None: the task's own); `clip_size`: a `runvocab.clip_format.CLIP_SIZES` name
    (None: the default); `grid_key`: an experiment's key for the run (`labelqueue.grid`);
    `dataset`: the dataset export a labelling-only run draws its pairs from (checked by
    `rundata.labelling.create_labelling_run`, which should be used to make one).
    The run's configuration is resolved against the presets here and stored with it
    (`labelqueue.run_config`). Invalid for a bad instruction or clip size; a ConfigError naming
    the field for a run no worker could train. Nothing is stored then."""
    stored_instruction = checked_instruction(instruction)
    checked_clip_size(clip_size)
    resolved = resolve(task=task, algo=algo, preset=preset, seed=seed, budget=budget,
                       teacher_params=teacher_params or {}, config=config or {})
    with transaction(session):
        run = Run(
            name=name,
            task=task,
            algo=algo,
            preset=preset,
            seed=seed,
            budget=budget,
            teacher=TeacherKind(teacher),
            teacher_params=json_object(teacher_params or {}),
            config=json_object(config or {}),
            resolved_config=resolved,
            status=RunStatus.QUEUED,
            instruction=stored_instruction,
            clip_size=clip_size,
            grid_key=grid_key,
            dataset=dataset,
        )
        session.add(run)
        session.flush()
        record_instruction(session, run)
        detach(session, run)
    return run


def read_run(session: Session, *, run_id: int) -> Run:
    """The run as stored now (NotFound if there is none)."""
    with reading(session):
        run = get_row(session, Run, run_id)
        detach(session, run)
    return run


def _saw_worker(session: Session, *, worker_id: str, now: datetime, run_id: int | None) -> None:
    # Only the worker itself writes its row (these run in its process, so the host is its
    # own), so get-then-add races with no other writer.
    worker = session.get(Worker, worker_id, populate_existing=True)
    if worker is None:
        session.add(Worker(id=worker_id, run_id=run_id, first_seen_at=now, last_seen_at=now,
                           host=HOST))
    else:
        worker.last_seen_at = now
        worker.run_id = run_id
        worker.host = HOST


def _claimable(worker_id: str, now: datetime,
               stale_after: float = DEAD_WORKER_AFTER_S) -> ColumnElement[bool]:
    """The runs `worker_id` may claim now: queued ones, running ones whose worker has not
    heartbeated for `stale_after` seconds or was released while paused, and its own."""
    dead = now - timedelta(seconds=stale_after)
    return and_(Run.algo != EXTERNAL, or_(
        Run.status == RunStatus.QUEUED,
        and_(Run.status == RunStatus.RUNNING, Run.heartbeat_at < dead),
        # Released while paused, then resumed by the operator: nobody holds it.
        and_(Run.status == RunStatus.RUNNING, Run.worker_id.is_(None)),
        and_(Run.status.in_(OWNED), Run.worker_id == worker_id),
    ))  # an external run is no worker's: its client pushes its pairs


def claim_run(session: Session, *, worker_id: str, stale_after: float = DEAD_WORKER_AFTER_S,
              skip: Collection[int] = ()) -> Run | None:
    """Take back a run this worker id already owns (the worker was restarted), else the oldest
    queued run, or a running one whose worker stopped heartbeating; none of the runs in `skip`
    (those the worker set aside while their skill snapshot is pretrained elsewhere).

    The run is owned by `worker_id` and becomes `running` (a paused or stopping run taken back
    keeps its status). None when there is nothing to do; an idle worker calls this in a loop,
    which also records that it is alive.
    """
    now = utcnow()
    claimable = _claimable(worker_id, now, stale_after)
    mine_first = case((Run.worker_id == worker_id, 0), else_=1)
    with transaction(session):
        candidates = session.scalars(
            select(Run.id).where(claimable, Run.id.not_in(list(skip)))
            .order_by(mine_first, Run.created_at, Run.id).limit(20)
        ).all()
        for run_id in candidates:
            won = changed(
                session,
                update(Run)
                .where(Run.id == run_id, claimable)
                .values(
                    status=case(
                        (Run.status == RunStatus.QUEUED, RunStatus.RUNNING.value),
                        else_=Run.status,
                    ),
                    worker_id=worker_id,
                    heartbeat_at=now,
                ),
            )
            if won:
                run = get_row(session, Run, run_id)
                if run.started_at is None:
                    run.started_at = now
                _saw_worker(session, worker_id=worker_id, now=now, run_id=run_id)
                detach(session, run)
                return run
        _saw_worker(session, worker_id=worker_id, now=now, run_id=None)
    return None


def other_claimable(session: Session, *, worker_id: str, besides: Collection[int]) -> bool:
    """Whether `worker_id` could claim a run other than those in `besides` now."""
    with reading(session):
        return session.scalar(
            select(Run.id).where(_claimable(worker_id, utcnow()), Run.id.not_in(list(besides)))
            .limit(1)) is not None


def _not_owner(session: Session, *, run_id: int, worker_id: str) -> Conflict:
    run = get_row(session, Run, run_id)
    return Conflict(f"run {run_id} belongs to worker {run.worker_id!r}, not {worker_id!r}")


def heartbeat(
    session: Session,
    *,
    run_id: int,
    worker_id: str,
    step: int,
    progress: Mapping[str, Any] | None = None,
) -> RunStatus:
    """Record that the owning worker is alive at `step`; the run's status, for it to obey.

    `paused`: stop training, keep heartbeating; `stopping`: checkpoint, then
    `finish_run(status="stopped")`; `stopped`: an operator forced the stop, so checkpoint and
    exit. Raises Conflict once the run belongs to another worker (it was requeued, or declared
    dead and claimed): this worker must then stop writing to it.
    """
    now = utcnow()
    values: dict[str, Any] = {"heartbeat_at": now, "step": int(step)}
    if progress is not None:
        values["progress"] = json_object(progress)
    with transaction(session):
        status = session.execute(
            update(Run)
            .where(Run.id == run_id, Run.worker_id == worker_id)
            .values(**values)
            .returning(Run.status),
            execution_options={"synchronize_session": False},
        ).scalar_one_or_none()
        if status is None:
            raise _not_owner(session, run_id=run_id, worker_id=worker_id)
        _saw_worker(session, worker_id=worker_id, now=now, run_id=run_id)
    return RunStatus(status)


def release_run(session: Session, *, run_id: int, worker_id: str,
                untouched: bool = False) -> Run:
    """The owning worker gives its run back at once, after a checkpoint (it was told to go:
    SIGTERM, a scheduler's preemption or time limit), or `untouched`, before it trained a step
    (it set the run aside while another worker pretrains its skill snapshot): then the run is
    as if never claimed, with no start time. The run keeps its step and progress and loses its
    worker: a running run is queued again, for the next worker to claim and resume from the
    checkpoint; a paused one stays paused (the operator's resume queues it for any worker); a
    stopping one, whose checkpoint is written, becomes stopped.

    Conflict when the run belongs to another worker (it was requeued or taken over meanwhile).
    """
    now = utcnow()
    with transaction(session):
        released = changed(
            session,
            update(Run)
            .where(Run.id == run_id, Run.worker_id == worker_id, Run.status.in_(OWNED))
            .values(
                status=case(
                    (Run.status == RunStatus.RUNNING, RunStatus.QUEUED.value),
                    (Run.status == RunStatus.STOPPING, RunStatus.STOPPED.value),
                    else_=Run.status,
                ),
                finished_at=case(
                    (Run.status == RunStatus.STOPPING, literal(now, UTCDateTime())),
                    else_=Run.finished_at,
                ),
                worker_id=None,
                heartbeat_at=None,
                **({"started_at": None} if untouched else {}),
            ),
        )
        if not released:
            raise _not_owner(session, run_id=run_id, worker_id=worker_id)
        run = get_row(session, Run, run_id)
        _saw_worker(session, worker_id=worker_id, now=now, run_id=None)
        detach(session, run)
    return run


def heartbeat_age(run: Run, now: datetime | None = None) -> float | None:
    """Seconds since the run's worker last heartbeat (None: no worker holds it)."""
    if run.heartbeat_at is None or run.worker_id is None:
        return None
    return ((now or utcnow()) - run.heartbeat_at).total_seconds()


def silent_holders(
    session: Session, *, worker_id: str, silent_after: float = SILENT_WORKER_AFTER_S
) -> list[Run]:
    """The running runs held by another worker that has not heartbeat for `silent_after`
    seconds (it may be dead; another worker may claim the run once the heartbeat is
    `DEAD_WORKER_AFTER_S` old), oldest heartbeat first."""
    quiet = utcnow() - timedelta(seconds=silent_after)
    with reading(session):
        runs = list(session.scalars(
            select(Run)
            .where(Run.status == RunStatus.RUNNING, Run.worker_id.is_not(None),
                   Run.worker_id != worker_id, Run.heartbeat_at < quiet)
            .order_by(Run.heartbeat_at, Run.id)
            .execution_options(populate_existing=True)
        ).all())
        detach(session, *runs)
    return runs


def set_run_status(session: Session, *, run_id: int, status: RunStatus | str) -> Run:
    """An operator's pause, resume, stop, cancel or requeue (see OPERATOR_MOVES).

    InvalidTransition for any other move; requeueing clears the worker, times and error.
    """
    target = RunStatus(status)
    with reading(session):
        external = get_row(session, Run, run_id).algo == EXTERNAL
    if external:  # no worker to acknowledge a stop, nor to claim it again
        target = {RunStatus.STOPPING: RunStatus.STOPPED,
                  RunStatus.QUEUED: RunStatus.RUNNING}.get(target, target)
    values: dict[str, Any] = {"status": target}
    if target is RunStatus.STOPPED:
        values["finished_at"] = utcnow()
    if target is RunStatus.QUEUED or external and target is RunStatus.RUNNING:
        values |= {"worker_id": None, "heartbeat_at": None, "finished_at": None, "error": None}
    with transaction(session):
        moved = changed(
            session,
            update(Run)
            .where(Run.id == run_id, Run.status.in_(
                EXTERNAL_MOVES.get(target, ()) if external else OPERATOR_MOVES.get(target, ())))
            .values(**values),
        )
        run = get_row(session, Run, run_id)
        if not moved:
            raise InvalidTransition(f"run {run_id} is {run.status}; it cannot be made {target}")
        detach(session, run)
    return run


def stop_run(session: Session, *, run_id: int, force: bool = False) -> Run:
    """An operator's stop, one conditional UPDATE that chooses from the run as it is then (a
    claim or a worker's end between a read and the move cannot turn it into a 409).

    Running or paused with a worker: stopping (the worker checkpoints, then ends it as stopped).
    Stopped at once: queued; running, paused or stopping with no worker holding it (released
    by SIGTERM or preemption, or an external run), which no worker would ever claim to end;
    stopping with `force` (its worker died before acknowledging). InvalidTransition otherwise.
    """
    live = Run.status.in_((RunStatus.RUNNING, RunStatus.PAUSED))
    unheld = Run.worker_id.is_(None)
    stopping = Run.status == RunStatus.STOPPING
    ends_now = or_(Run.status == RunStatus.QUEUED, and_(live, unheld),
                   stopping if force else and_(stopping, unheld))
    now = utcnow()
    with transaction(session):
        moved = changed(
            session,
            update(Run)
            .where(Run.id == run_id, or_(live, ends_now))
            .values(
                status=case((ends_now, RunStatus.STOPPED.value),
                            else_=RunStatus.STOPPING.value),
                finished_at=case((ends_now, literal(now, UTCDateTime())),
                                 else_=Run.finished_at),
            ),
        )
        run = get_row(session, Run, run_id)
        if not moved:
            raise InvalidTransition(f"run {run_id} is {run.status}; it cannot be stopped")
        detach(session, run)
    return run


def finish_run(
    session: Session,
    *,
    run_id: int,
    worker_id: str,
    status: RunStatus | str = RunStatus.FINISHED,
    error: str | None = None,
) -> Run:
    """The owning worker's last word: finished, failed (with `error`) or stopped."""
    target = RunStatus(status)
    if target not in WORKER_ENDS:
        raise InvalidTransition(f"a worker ends a run as one of {', '.join(WORKER_ENDS)}")
    now = utcnow()
    with transaction(session):
        ended = changed(
            session,
            update(Run)
            .where(Run.id == run_id, Run.worker_id == worker_id, Run.status.in_(OWNED))
            .values(status=target, finished_at=now, error=error),
        )
        run = get_row(session, Run, run_id)
        if not ended:
            if run.worker_id != worker_id:
                raise _not_owner(session, run_id=run_id, worker_id=worker_id)
            raise InvalidTransition(f"run {run_id} is {run.status}; it cannot be made {target}")
        _saw_worker(session, worker_id=worker_id, now=now, run_id=None)
        detach(session, run)
    return run


def set_teacher(
    session: Session,
    *,
    run_id: int,
    teacher: TeacherKind | str,
    params: Mapping[str, Any] | None = None,
) -> Run:
    """Switch who answers a run's queries; the worker reads it when it opens its next round.
    The run's stored configuration takes the new parameters (a ConfigError names a bad one),
    which replace its `config`'s own (`teacher.eps`). InvalidTransition unless the run is one
    a worker still trains (`TEACHABLE`): a run that ended keeps the teacher it trained with."""
    with transaction(session):
        config, resolved = with_teacher(get_row(session, Run, run_id), params or {})
        moved = changed(session, update(Run).where(Run.id == run_id, Run.status.in_(TEACHABLE))
                        .values(teacher=TeacherKind(teacher), config=config,
                                teacher_params=json_object(params or {}),
                                **({} if resolved is None else {"resolved_config": resolved})))
        run = get_row(session, Run, run_id)
        if not moved:
            raise InvalidTransition(f"run {run_id} is {run.status}: its teacher changes only "
                                    "while it is queued, running or paused (requeue it first)")
        detach(session, run)
    return run

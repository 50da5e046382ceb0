"""Why a run is waiting, and what its labellers' pages are waiting for; the workers as last seen.

A run's activity is read from its row (status, the worker's heartbeat and its `progress`), its
open queries and its recent labels: waiting for a free worker, pretraining skills (with an
estimate from the worker's own pace), waiting for N answers from K active labellers (and how
many are paused by check pairs), exploring before the first round or training until the next
(with an estimate), or a worker that went silent. The operator's run page shows it; the label
page shows a labeller the same in their terms when there is nothing for them to label.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, Literal

from sqlalchemy import func, select, union
from sqlalchemy.orm import Session

from labelqueue.models import (
    Label,
    LabellerPause,
    LabelSource,
    Query,
    QueryStatus,
    Run,
    RunStatus,
    TeacherKind,
    Worker,
    utcnow,
)
from labelqueue.runs import DEAD_WORKER_AFTER_S, EXTERNAL, budget_spent
from labelqueue.transaction import reading

LIVE_WORKER_S = 60.0
"""a worker heard from within this is alive (they report every few seconds, even when idle)"""
RECENT_WORKER_S = 86_400.0
"""the workers panel lists those heard from within this by default (a day: dead ones stay in
sight long enough to be noticed)"""
ACTIVE_LABELLER_S = 120.0
"""a labeller is active while leasing or answering: they answered one of the run's pairs
within this, or hold a live lease taken within this (a page left open renews its leases, but
the lease it took long ago says nobody answers there)"""

WorkerStateName = Literal["training", "idle", "silent", "dead"]


@dataclass(frozen=True)
class WorkerState:
    """A worker as last seen: `training` or `idle` when heard from within `LIVE_WORKER_S`,
    `silent` after that, `dead` after `DEAD_WORKER_AFTER_S` (another worker may take its run)."""

    id: str
    host: str | None
    run_id: int | None
    first_seen_at: datetime
    last_seen_at: datetime
    silent_s: float
    state: WorkerStateName


def _worker_state(worker: Worker, now: datetime) -> WorkerState:
    silent = max(0.0, (now - worker.last_seen_at).total_seconds())
    state: WorkerStateName = (
        "dead" if silent > DEAD_WORKER_AFTER_S else "silent" if silent > LIVE_WORKER_S
        else "training" if worker.run_id is not None else "idle")
    return WorkerState(worker.id, worker.host, worker.run_id, worker.first_seen_at,
                       worker.last_seen_at, silent, state)


def list_workers(session: Session, now: datetime | None = None,
                 seen_within_s: float | None = RECENT_WORKER_S,
                 limit: int | None = None) -> list[WorkerState]:
    """The workers heard from within `seen_within_s` (None: every one that ever reported), the
    most recently seen first, at most `limit` of them. Each worker process has a row of its own
    (`host-pid`) that is never deleted, so every restart adds one: listing them all grows for
    ever."""
    now = now or utcnow()
    statement = select(Worker).order_by(Worker.last_seen_at.desc(), Worker.id).limit(limit)
    if seen_within_s is not None:
        statement = statement.where(Worker.last_seen_at >= now - timedelta(seconds=seen_within_s))
    with reading(session):
        workers = list(session.scalars(statement))
        session.expunge_all()
    return [_worker_state(worker, now) for worker in workers]


Phase = Literal["queued", "starting", "pretraining", "labelling", "exploring", "training",
                "paused", "stopping", "silent", "stopped", "finished", "failed"]


@dataclass(frozen=True)
class Activity:
    """What a run is doing, or waiting for, now."""

    run_id: int
    phase: Phase
    text: str
    """one sentence for the operator"""
    answers_needed: int = 0
    """answers the open round still waits for (check pairs aside)"""
    pairs_open: int = 0
    pairs_unrendered: int = 0
    labellers_active: int = 0
    labellers_paused: int = 0
    eta_s: float | None = None
    """seconds until the phase ends (pretraining, or until the next round), when known"""
    workers_alive: int = 0
    workers_idle: int = 0
    queued_ahead: int = 0
    """queued runs older than this one (a queued run)"""


def _eta(remaining: float, rate: Any) -> float | None:
    if not isinstance(rate, int | float) or rate <= 0 or remaining <= 0:
        return None
    return remaining / float(rate)


def about(seconds: float | None) -> str:
    """"about 40 s", "about 12 min", "about 2.5 h"; "" when unknown."""
    if seconds is None:
        return ""
    if seconds < 90:
        return f"about {max(5, round(seconds / 5) * 5):.0f} s"
    if seconds < 5400:
        return f"about {round(seconds / 60):.0f} min"
    return f"about {seconds / 3600:.1f} h"


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def runs_activity(session: Session, runs: list[Run], now: datetime | None = None) -> list[Activity]:
    """The activity of each run, in the order given."""
    now = now or utcnow()
    if not runs:
        return []
    ids = [run.id for run in runs]
    recent = now.timestamp() - ACTIVE_LABELLER_S
    with reading(session):
        open_rows = session.execute(
            select(Query.run_id, func.count(Query.id),
                   func.coalesce(func.sum(Query.needs_labels - Query.label_count), 0),
                   func.sum((Query.first_clip.is_(None) | Query.second_clip.is_(None))
                            .cast(Query.needs_labels.type)))
            .where(Query.run_id.in_(ids), Query.gold.is_(False),
                   Query.status.in_((QueryStatus.PENDING, QueryStatus.LEASED)))
            .group_by(Query.run_id)
        ).all()
        since = datetime.fromtimestamp(recent, now.tzinfo)
        answering = union(
            select(Label.run_id, Label.labeller_id).where(
                Label.run_id.in_(ids), Label.source == LabelSource.HUMAN,
                Label.answered_at > since),
            select(Query.run_id, Query.lease_holder.label("labeller_id")).where(
                Query.run_id.in_(ids), Query.lease_holder.is_not(None),
                Query.lease_expires_at > now, Query.leased_at > since),
        ).subquery()
        paused_rows = session.execute(
            select(LabellerPause.run_id, LabellerPause.labeller_id)
            .where(LabellerPause.run_id.in_(ids))).all()
        active_rows = session.execute(select(answering.c.run_id, answering.c.labeller_id)).all()
        # Only the live ones count, and their number is bounded; the dead are not.
        workers = list(session.scalars(select(Worker).where(
            Worker.last_seen_at >= now - timedelta(seconds=LIVE_WORKER_S))))
        queued = session.execute(
            select(Run.id, Run.created_at).where(Run.status == RunStatus.QUEUED)
            .order_by(Run.created_at, Run.id)).all()
        session.expunge_all()
    opened = {run_id: (int(n), int(needed), int(unrendered or 0))
              for run_id, n, needed, unrendered in open_rows}
    paused: dict[int, set[int]] = {}
    for run_id, labeller_id in paused_rows:
        paused.setdefault(run_id, set()).add(labeller_id)
    active: dict[int, set[int]] = {}
    for run_id, labeller_id in active_rows:
        if labeller_id not in paused.get(run_id, set()):
            active.setdefault(run_id, set()).add(labeller_id)
    states = [_worker_state(worker, now) for worker in workers]
    alive = [w for w in states if w.state in ("training", "idle")]
    idle = [w for w in alive if w.state == "idle"]
    queue_order = [run_id for run_id, _ in queued]
    return [_activity(run, now, opened.get(run.id, (0, 0, 0)), len(active.get(run.id, ())),
                      len(paused.get(run.id, ())), len(alive), len(idle),
                      queue_order.index(run.id) if run.id in queue_order else 0)
            for run in runs]


def _activity(run: Run, now: datetime, opened: tuple[int, int, int], active: int, paused: int,
              alive: int, idle: int, ahead: int) -> Activity:
    pairs, needed, unrendered = opened
    counts = {"answers_needed": needed, "pairs_open": pairs, "pairs_unrendered": unrendered,
              "labellers_active": active, "labellers_paused": paused, "workers_alive": alive,
              "workers_idle": idle, "queued_ahead": ahead}
    progress = run.progress or {}
    status = RunStatus(run.status)

    def make(phase: Phase, text: str, eta: float | None = None) -> Activity:
        return Activity(run.id, phase, text, eta_s=eta, **counts)

    if status is RunStatus.QUEUED:
        if alive == 0:
            return make("queued", "waiting for a worker: none is running (start one with "
                                  "`sepoa worker`)")
        if idle == 0:
            return make("queued", f"waiting for a free worker: {_plural(alive, 'worker')} "
                                  f"alive, all busy" + (f"; {ahead} queued run"
                                                        f"{'' if ahead == 1 else 's'} ahead"
                                                        if ahead else ""))
        return make("queued", "waiting for a free worker to claim it (one is idle)")
    if status is RunStatus.STOPPING:
        return make("stopping", "stopping: the worker checkpoints, then ends it")
    if status in (RunStatus.STOPPED, RunStatus.FINISHED, RunStatus.FAILED):
        return make(status.value, status.value)  # type: ignore[arg-type]
    silent = (now - run.heartbeat_at).total_seconds() if run.heartbeat_at else None
    if silent is not None and silent > LIVE_WORKER_S:
        dead = silent > DEAD_WORKER_AFTER_S
        return make("silent", f"its worker {run.worker_id} has not reported for "
                              f"{about(silent).removeprefix('about ')}"
                              + ("; another worker may take the run over" if dead else ""))
    if status is RunStatus.PAUSED:
        return make("paused", "paused by an operator" + (
            f"; {_plural(needed, 'answer')} still wanted" if needed else ""))
    if needed > 0:
        if run.teacher == TeacherKind.SCRIPTED:
            return make("labelling", f"the scripted teacher answers {_plural(pairs, 'pair')}")
        text = (f"waiting for {_plural(needed, 'answer')} from "
                f"{_plural(active, 'active labeller')}")
        if paused:
            text += f" ({paused} paused by check pairs)"
        if unrendered:
            text += f"; {unrendered} of {_plural(pairs, 'pair')} still rendering"
        return make("labelling", text)
    if run.algo == EXTERNAL:  # no worker: its client pushes pairs when it has some
        if budget_spent(run):
            return make("training", "the label budget is spent, no more pairs")
        return make("training", "waiting for its client to push pairs")
    step = int(run.step or 0)
    pre_step = progress.get("pretraining_step")
    pre_total = progress.get("pretraining_steps")
    if step == 0 and pre_step is not None:
        if pre_step == 0 and not progress.get("pretraining_fps"):
            return make("pretraining", "pretraining skills: another run is making this "
                                       "task's skill snapshot; it waits for it")
        eta = _eta((pre_total or 0) - pre_step, progress.get("pretraining_fps"))
        where = f" (step {pre_step:,} of {pre_total:,})" if pre_total else ""
        return make("pretraining", f"pretraining skills{where}"
                    + (f", {about(eta)} left" if eta else ""), eta)
    if step == 0 and not progress:
        return make("starting", "starting: building the environment and the agent")
    next_round = progress.get("next_round_step")
    eta = _eta((next_round or 0) - step, progress.get("steps_per_s", progress.get("fps")))
    if budget_spent(run):
        return make("training", "training: the label budget is spent, no more pairs")
    if progress.get("round") is None:
        return make("exploring", "exploring before its first round of pairs"
                    + (f", due in {about(eta)}" if eta else ""), eta)
    return make("training", "training on the answers" + (
        f"; next round in {about(eta)}" if eta else ""), eta)


@dataclass(frozen=True)
class Waiting:
    """Why a labeller has nothing to label now, in their terms."""

    reason: str
    """a phase of the run (`Activity.phase`) or "no_run" """
    text: str
    run_id: int | None = None
    eta_s: float | None = None


WAITING_ORDER = ("labelling", "training", "exploring", "pretraining", "starting", "queued",
                 "paused", "silent", "stopping")
"""which run a labeller hears about when several could give them pairs: the soonest first"""


def labeller_waiting(session: Session, *, run_id: int | None) -> Waiting:
    """Why there is nothing to label on the run (or on any run taught by people)."""
    with reading(session):
        where = [Run.id == run_id] if run_id is not None else [Run.teacher == TeacherKind.HUMAN]
        runs = list(session.scalars(select(Run).where(
            *where, Run.status.in_((RunStatus.QUEUED, RunStatus.RUNNING, RunStatus.PAUSED,
                                    RunStatus.STOPPING)))))
        session.expunge_all()
    if not runs:
        return Waiting("no_run", "No run is open for labelling right now. New pairs appear "
                                 "here by themselves when one starts.")
    activities = runs_activity(session, runs)
    best = min(activities, key=lambda a: (WAITING_ORDER.index(a.phase)
                                          if a.phase in WAITING_ORDER else 99,
                                          a.eta_s if a.eta_s is not None else 1e12))
    eta = f" (next pairs in {about(best.eta_s)})" if best.eta_s else ""
    text = {
        "labelling": "The rest of this round's pairs are with other labellers. New pairs come "
                     "once the trainer has their answers and has learnt from them.",
        "training": f"The trainer is learning from the answers so far{eta}.",
        "exploring": f"The trainer is exploring before it asks its first questions{eta}.",
        "pretraining": "The trainer is first pretraining its skills, before it asks anything"
                       + (f": {about(best.eta_s)} left" if best.eta_s else "") + ".",
        "starting": "The trainer is starting up.",
        "queued": "The run is waiting for a free trainer to start it.",
        "paused": "The run is paused by its operator.",
        "silent": "The trainer has stopped reporting; the operator can see this too.",
        "stopping": "The run is stopping.",
    }.get(best.phase, best.text)
    if best.phase == "labelling" and best.pairs_unrendered and best.pairs_unrendered == \
            best.pairs_open:
        text = "The trainer is rendering the next clips."
    if best.phase == "training" and "budget" in best.text:
        text = "The run's label budget is spent: it asks for no more answers."
    return Waiting(best.phase, text, best.run_id, best.eta_s)

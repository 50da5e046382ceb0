"""Experiments' runs: a run enqueued with a grid key (`<spec name>/<run folder>`) exists once.

Enqueueing a grid again finds each run by its key instead of adding it; two launchers racing on
one spec are decided by the key's unique index (the loser reads the winner's row). A grid whose
definition changed may give a key to a new run only after the old run lets go of it
(`release_grid_key`).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict, NotFound
from labelqueue.models import Run, RunStatus, utcnow
from labelqueue.runs import OWNED, create_run
from labelqueue.transaction import changed, detach, get_row, reading, transaction


def find_grid_run(session: Session, *, grid_key: str) -> Run | None:
    with reading(session):
        run = session.scalars(select(Run).where(Run.grid_key == grid_key)).one_or_none()
        if run is not None:
            detach(session, run)
    return run


def grid_runs(session: Session, *, prefix: str) -> dict[str, Run]:
    """The runs whose grid key starts with `prefix` (a spec's `<name>/`), by key. Compared as
    text, not with LIKE, which SQLite reads case-insensitively: `Grid/` is not `grid/`."""
    with reading(session):
        rows = list(session.scalars(
            select(Run).where(func.substr(Run.grid_key, 1, len(prefix)) == prefix)
            .execution_options(populate_existing=True)))
        detach(session, *rows)
    return {run.grid_key: run for run in rows if run.grid_key is not None}


def enqueue_grid_run(session: Session, *, grid_key: str, **fields: Any) -> tuple[Run, bool]:
    """(the run with this key, whether this call created it): a queued run made with
    `create_run(**fields)`, unless the key is taken, whatever that run's state."""
    existing = find_grid_run(session, grid_key=grid_key)
    if existing is not None:
        return existing, False
    try:
        return create_run(session, grid_key=grid_key, **fields), True
    except IntegrityError:  # another launcher enqueued it just now
        found = find_grid_run(session, grid_key=grid_key)
        if found is None:
            raise
        return found, False


def release_grid_key(session: Session, *, run_id: int) -> Run:
    """The run lets go of its grid key (kept as a plain run); a queued one is stopped first, so
    no worker trains it. Conflict while a worker owns it (running, paused or stopping)."""
    with transaction(session):
        run = get_row(session, Run, run_id)
        if run.grid_key is None:
            raise NotFound(f"run {run_id} has no grid key")
        values: dict[str, Any] = {"grid_key": None}
        if run.status is RunStatus.QUEUED:
            values |= {"status": RunStatus.STOPPED, "finished_at": utcnow()}
        done = changed(session, update(Run).where(Run.id == run_id, Run.status.not_in(OWNED))
                       .values(**values))
        if not done:
            raise Conflict(f"run {run_id} ({run.grid_key}) is {run.status} on worker "
                           f"{run.worker_id!r}; stop it first")
        run = get_row(session, Run, run_id)
        detach(session, run)
    return run


ADOPTABLE = (RunStatus.QUEUED, RunStatus.FAILED, RunStatus.STOPPED)
"""statuses of a grid run no worker holds and that has not finished here"""


def adopt_finished_grid_run(session: Session, *, run_id: int, step: int,
                            labels_used: int) -> Run:
    """A queued, failed or stopped grid run whose results folder already holds its finished
    results (carried from another queue database: another machine, a lost database) is
    recorded as finished at `step`, so no worker trains it again. Conflict for a run in any
    other state."""
    with transaction(session):
        now = utcnow()
        done = changed(session, update(Run).where(Run.id == run_id, Run.status.in_(ADOPTABLE))
                       .values(status=RunStatus.FINISHED, step=step, labels_used=labels_used,
                               started_at=now, finished_at=now, worker_id=None,
                               heartbeat_at=None, error=None))
        run = get_row(session, Run, run_id)
        if not done:
            raise Conflict(f"run {run_id} ({run.grid_key}) is {run.status}, not queued, "
                           "failed or stopped")
        detach(session, run)
    return run

"""A spec's grid as runs in the queue database: enqueued once each, trained by any worker.

Each run of the grid is a queued run with the scripted teacher (`teacher.eps` from the grid) and
the grid key `<spec name>/<run folder>`; the key is unique in the database, so enqueueing the
spec again adds nothing, and two launchers on one spec enqueue each run once (the queue's claim
then gives each run to one worker). A worker trains a keyed run in `<results>/<grid key>`
(`trainer.worker`), so the grid lands in `<results>/<spec name>/<run folder>/`.

The row is the run's definition: a spec that would give an existing run another one (a changed
override, more steps) is refused, listing the runs, unless forced; forcing lets the old rows go
(`labelqueue.release_grid_key`), deletes their folders and enqueues the new definition. Runs
that failed or were stopped are queued again; a worker resumes them from their checkpoint. The
stopped runs of seeds a recorded stop rule leaves out (`experiments.stop_rule`) stay stopped.
A run not finished in this database whose folder holds its finished results (copied in from
another machine) is recorded as finished, whether queued, failed or stopped here: a worker
would start it afresh in a folder without a checkpoint, deleting those results.
"""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from experiments.progress import (
    duration_text,
    episode_rows,
    pretraining_left,
    reward_epochs,
    seconds_left,
    seeds_before_stop,
    summary,
    training_clock,
    training_rate,
)
from experiments.sessions import worked
from experiments.spec import Run as GridRun
from experiments.spec import Spec, SpecError, flatten
from labelqueue import (
    DEAD_WORKER_AFTER_S,
    SILENT_WORKER_AFTER_S,
    Conflict,
    Run,
    RunStatus,
    adopt_finished_grid_run,
    enqueue_grid_run,
    grid_runs,
    heartbeat_age,
    release_grid_key,
    set_run_status,
)
from labelqueue.models import utcnow
from runvocab.config import apply_overrides, to_dict
from runvocab.queued_run import TOP_LEVEL_FIELDS
from runvocab.snapshot_names import shared_snapshot_dir

RETRIED = (RunStatus.FAILED, RunStatus.STOPPED)
"""statuses a run is queued again from when its spec is run again"""
ADOPTABLE = (RunStatus.QUEUED, *RETRIED)
"""statuses of a run recorded as finished when its folder holds its finished results"""


def grid_key(spec: Spec, run: GridRun) -> str:
    """`<spec name>/<run folder>`: the run's key in the database and its folder under results."""
    return f"{spec.name}/{run.dir.as_posix()}"


def queued_fields(spec: Spec, run: GridRun) -> dict[str, Any]:
    """`create_run`'s arguments for a grid run: scripted teacher, the grid's eps, the budget as
    the run's own (the budgets axis, else the task's and preset's), the rest as config."""
    config = {path: value for path, value in run.config_overrides().items()
              if path not in TOP_LEVEL_FIELDS and path != "teacher.eps"}
    return {"name": f"{spec.name}: {run.dir.as_posix()}", "task": run.task, "algo": run.algo,
            "preset": run.preset, "seed": run.seed,
            "budget": run.budget if run.budget is not None else run.config().feedback.budget,
            "teacher": "scripted", "teacher_params": {"eps": run.eps},
            "config": json.loads(json.dumps(config, default=str))}


DEFINING = ("task", "algo", "preset", "seed", "budget", "teacher_params", "config")


def definition(fields: dict[str, Any] | Run) -> str:
    """The fields that define a run's results, as comparable text."""
    get = fields.get if isinstance(fields, dict) else lambda name: getattr(fields, name)
    return json.dumps({name: get(name) for name in DEFINING}, sort_keys=True, default=str)


@dataclass
class Enqueued:
    """What enqueueing a spec did, by grid key."""

    created: list[str] = field(default_factory=list)
    requeued: list[str] = field(default_factory=list)
    """failed or stopped before: queued again (a worker resumes from the checkpoint)"""
    replaced: list[str] = field(default_factory=list)
    """redefined with --force: the old run let go of its key, its folder was deleted"""
    present: dict[str, RunStatus] = field(default_factory=dict)
    """already queued, running or finished: left as they are"""
    adopted: list[str] = field(default_factory=list)
    """queued, failed or stopped, but its folder holds the finished results of this very run
    (carried from another queue database): recorded as finished, not trained again"""
    left_out: list[str] = field(default_factory=list)
    """stopped runs of seeds the recorded stop rule leaves out: left stopped"""


HOST_FIELDS = ("run_dir", "threads", "device", "skill.snapshot_dir")
"""config fields a worker sets for its host: they differ between machines, not between results"""


def finished_results(results: Path, spec: Spec, run: GridRun) -> dict[str, Any] | None:
    """The done.json of `run`'s folder when it holds this run's finished results: its
    config.json is the spec's configuration of the run (host fields aside). None otherwise."""
    folder = results / grid_key(spec, run)
    try:
        done = json.loads((folder / "done.json").read_text())
        stored = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError):
        return None
    expected = json.loads(json.dumps(to_dict(run.config()), default=str))
    mine, theirs = flatten(expected), flatten(stored)
    for name in HOST_FIELDS:
        mine.pop(name, None)
        theirs.pop(name, None)
    return done if mine == theirs else None


def shown_status(row: Run | None, results: Path, spec: Spec, run: GridRun) -> str:
    """`run`'s status in the database; without a row there, "finished" when its folder holds
    its finished results (copied in from another host; enqueueing would record it so), else
    "not queued"."""
    if row is not None:
        return str(row.status)
    return "finished" if finished_results(results, spec, run) is not None else "not queued"


def conflicts(spec: Spec, sessions: sessionmaker[Session]) -> dict[str, Run]:
    """The spec's runs whose row in the database has another definition, by grid key."""
    with sessions() as session:
        rows = grid_runs(session, prefix=f"{spec.name}/")
    out = {}
    for run in spec.runs():
        key = grid_key(spec, run)
        if key in rows and definition(rows[key]) != definition(queued_fields(spec, run)):
            out[key] = rows[key]
    return out


def _describe(row: Run, fields: dict[str, Any]) -> str:
    stored = json.loads(definition(row))
    new = json.loads(definition(fields))
    diffs = [f"{name} {stored[name]!r} -> {new[name]!r}" for name in DEFINING
             if stored[name] != new[name]]
    return f"run {row.id}, {row.status}: " + "; ".join(diffs)


def enqueue_spec(spec: Spec, sessions: sessionmaker[Session], results: Path,
                 force: bool = False, dry_run: bool = False,
                 left_out: Iterable[int] = ()) -> Enqueued:
    """Put the spec's grid in the queue (see the module docstring); SpecError for a redefined
    run without `force`, or one a worker still owns. `left_out`: the seeds the grid's recorded
    stop rule leaves out, whose stopped runs stay stopped. Nothing is written on a dry run."""
    left_out = set(left_out)
    clash = conflicts(spec, sessions)
    runs = {grid_key(spec, run): run for run in spec.runs_seed_first()}
    fields = {key: queued_fields(spec, run) for key, run in runs.items()}
    if clash and not force:
        lines = [f"{key}: {_describe(row, fields[key])}" for key, row in clash.items()]
        shown = "\n  ".join(lines[:5]) + (f"\n  ... {len(lines) - 5} more"
                                          if len(lines) > 5 else "")
        raise SpecError(f"the queue holds {len(clash)} run(s) of spec {spec.name!r} with "
                        f"another definition:\n  {shown}\nuse another spec name, or --force to "
                        "delete those runs and train them again")
    # Every clash is checked before any is let go: a held one found half-way would leave the
    # runs before it released and their folders deleted.
    held = [f"{key}: run {row.id} is {row.status} on worker {row.worker_id!r}"
            for key, row in clash.items() if row.status in HELD]
    if held:
        raise SpecError(f"cannot redefine {len(held)} run(s) a worker holds (nothing was "
                        f"changed): {'; '.join(held)}; stop them first")
    out = Enqueued()
    if dry_run:
        with sessions() as session:
            rows = grid_runs(session, prefix=f"{spec.name}/")
        for key in fields:
            if key in clash:
                out.replaced.append(key)
            elif key not in rows:
                out.created.append(key)
            elif rows[key].status is RunStatus.STOPPED and runs[key].seed in left_out:
                out.left_out.append(key)
            elif rows[key].status in RETRIED:
                out.requeued.append(key)
            else:
                out.present[key] = rows[key].status
        return out
    with sessions() as session:
        for key, row in clash.items():
            try:
                release_grid_key(session, run_id=row.id)
            except Conflict as err:
                raise SpecError(f"cannot redefine {key}: {err}") from None
            shutil.rmtree(results / key, ignore_errors=True)
            out.replaced.append(key)
        for key, values in fields.items():
            row, created = enqueue_grid_run(session, grid_key=key, **values)
            done = (finished_results(results, spec, runs[key])
                    if row.status in ADOPTABLE and key not in clash else None)
            if done is not None:
                adopt_finished_grid_run(session, run_id=row.id, step=int(done.get("step", 0)),
                                        labels_used=int(done.get("labels_used", 0)))
                out.adopted.append(key)
            elif created:
                if key not in clash:
                    out.created.append(key)
            elif row.status is RunStatus.STOPPED and runs[key].seed in left_out:
                out.left_out.append(key)
            elif row.status in RETRIED:
                set_run_status(session, run_id=row.id, status=RunStatus.QUEUED)
                out.requeued.append(key)
            else:
                out.present[key] = row.status
    return out


def spec_rows(spec: Spec, sessions: sessionmaker[Session]) -> dict[str, Run]:
    with sessions() as session:
        return grid_runs(session, prefix=f"{spec.name}/")


HELD = (RunStatus.RUNNING, RunStatus.PAUSED, RunStatus.STOPPING)
"""the statuses in which a worker holds a run, and its heartbeat age tells something"""


def _heartbeat(row: Run | None, now: datetime) -> tuple[str, str | None]:
    """A run's heartbeat cell, and a line about its worker when that worker has gone silent
    (it may be dead) or is presumed dead (another worker may take the run over)."""
    age = None if row is None else heartbeat_age(row, now)
    if row is None or age is None or row.status not in HELD:
        return "-", None
    cell = duration_text(age)
    if row.status is not RunStatus.RUNNING or age <= SILENT_WORKER_AFTER_S:
        return cell, None
    if age > DEAD_WORKER_AFTER_S:
        return f"{cell} DEAD", (f"  {row.grid_key}: worker {row.worker_id} silent for "
                                f"{cell}, presumed dead: the next worker to look takes the run "
                                "over from its checkpoint")
    left = duration_text(math.ceil(DEAD_WORKER_AFTER_S - age))
    return f"{cell} silent", (f"  {row.grid_key}: worker {row.worker_id} silent for {cell}: "
                              f"stopped or dead? Another worker may take the run over in "
                              f"{left} unless it comes back")


def training_workers(rows: Iterable[Run], now: datetime) -> set[str]:
    """The workers training a run now (a heartbeat within `SILENT_WORKER_AFTER_S`; one
    silent longer, killed a moment ago or stopped, trains nothing): the ones the grid's time
    left is divided among."""
    return {row.worker_id for row in rows
            if row.status is RunStatus.RUNNING and row.worker_id
            and (age := heartbeat_age(row, now)) is not None and age <= SILENT_WORKER_AFTER_S}


TAKEN = (RunStatus.RUNNING, RunStatus.PAUSED, RunStatus.STOPPING, RunStatus.FINISHED)
"""statuses only a worker's claim leads to (a queued run an operator stops or fails is not)"""


def started_seeds(spec: Spec, rows: dict[str, Run], results: Path) -> set[int]:
    """Seeds with a run that a worker has taken (`rows`: the spec's runs in the queue): its
    folder exists, or it is held or ended."""
    started = set()
    for run in spec.runs():
        key = grid_key(spec, run)
        row = rows.get(key)
        if (results / key).exists() or (row is not None and row.status in TAKEN):
            started.add(run.seed)
    return started


def status_table(spec: Spec, sessions: sessionmaker[Session], results: Path,
                 rule_line: str | None = None, rule_worked_s: float | None = None,
                 left_out: Collection[int] = ()) -> str:
    """A table of the spec's runs: their status in the database (or "not queued"), the step
    reached of the planned steps, the worker and how long ago it heartbeat (flagged `silent`
    past `SILENT_WORKER_AFTER_S`, `DEAD` past `DEAD_WORKER_AFTER_S`), whether the folder
    holds a checkpoint (and, inside a round, the reward epoch its training has saved), and
    about how long the run has left to train, its skill pretraining included
    (`experiments.progress`);
    then the time the grid has left, and `rule_line` (its stop rule's state) with, given
    `rule_worked_s` (the hours it counts, not spent yet), which seeds it lets start at these
    estimates. The unfinished runs of the seeds a reached stop rule leaves out (`left_out`)
    will not train: their time left says so, and the grid's does not count them."""
    rows = spec_rows(spec, sessions)
    now = utcnow()
    header = ("task", "variant", "eps", "budget", "seed", "status", "step", "worker",
              "heartbeat", "folder", "left")
    counts: dict[str, int] = {}
    lines, silent, progress = [], [], []
    for run in spec.runs():
        key = grid_key(spec, run)
        row = rows.get(key)
        status = shown_status(row, results, spec, run)
        counts[status] = counts.get(status, 0) + 1
        folder = results / key
        done = (folder / "done.json").exists()
        held = ("done" if done else
                "checkpoint" if (folder / "checkpoint.pt").exists() else
                "-" if not folder.exists() else "started")
        if not done and (epochs := reward_epochs(folder)) is not None:
            held += f", round: reward epoch {epochs[0]}/{epochs[1]}"
        if row is not None and row.status is RunStatus.RUNNING and not row.step:
            # An S-EPOA run pretraining its skill snapshot first (the worker's heartbeat).
            pre = row.progress or {}
            at, of = pre.get("pretraining_step"), pre.get("pretraining_steps")
            if at is not None and of and at < of:
                held += f", pretraining {at}/{of}"
        beat, note = _heartbeat(row, now)
        if note is not None:
            silent.append(note)
        reached = row.step if row is not None else 0
        episodes = episode_rows(folder)  # read once, for both
        progress.append((key, run.steps, reached, done, training_rate(folder, episodes),
                         training_clock(folder, episodes)))
        lines.append([run.task, run.variant, f"{run.eps:g}",
                      "-" if run.budget is None else str(run.budget), str(run.seed), status,
                      f"{reached}/{run.steps}",
                      (row.worker_id or "-") if row is not None else "-", beat, held])
    left = seconds_left(progress)
    # Each run's snapshot where the grid's workers keep it (trainer.worker.run_config).
    waits = pretraining_left(
        (grid_key(spec, run),
         apply_overrides(run.config(), shared_snapshot_dir(run.overrides, results)))
        for run in spec.runs() if not (results / grid_key(spec, run) / "done.json").exists())
    for key, wait in waits.items():
        training = left[key]
        left[key] = None if wait is None or training is None else training + wait
    ruled_out = {grid_key(spec, run) for run in spec.runs() if run.seed in left_out}
    for line, (key, _, _, done, _, _) in zip(lines, progress, strict=True):
        if not done and key in ruled_out:
            del left[key]
            left.by_rate.discard(key)
            line.append("left out")
            continue
        seconds = left[key]
        line.append("-" if done else "?" if seconds is None else duration_text(seconds))
    widths = [max(len(r[i]) for r in [header, *lines]) for i in range(len(header))]
    text = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
            for r in [header, *lines]]
    summary_line = ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))
    live_workers = training_workers(rows.values(), now)
    workers = len(live_workers)
    errors = [f"  {key}: {row.error}" for key, row in sorted(rows.items())
              if row.status is RunStatus.FAILED and row.error]
    period = worked(results / spec.name)
    ruled = [rule_line] if rule_line else []
    if rule_line and rule_worked_s is not None:
        ruled.append(stop_forecast(spec, rows, results, left, live_workers, rule_worked_s))
    return "\n".join([f"{spec.name}: {len(lines)} runs: {summary_line}", *text,
                      summary(left, workers, len(left.by_rate),
                              sum(line[-1] == "left out" for line in lines))]
                     + ([period.text(duration_text(period.seconds))] if period else [])
                     + ruled
                     + (["failed:", *errors] if errors else [])
                     + (["workers gone silent:", *silent] if silent else []))


def stop_forecast(spec: Spec, rows: dict[str, Run], results: Path,
                  left: dict[str, float | None], live_workers: set[str], worked_s: float) -> str:
    """Which seeds the stop rule lets start (`seeds_before_stop`): the workers training now
    finish the runs they hold, then claim the queued runs in the queue's order (its claim
    takes the oldest first), with those of silent or dead workers, which it takes over."""
    assert spec.stop_after_hours is not None
    if not live_workers:
        return "forecast: none while no worker trains"
    keys = {grid_key(spec, run): run for run in spec.runs()}
    held = [key for key, row in rows.items()
            if key in keys and row.status is RunStatus.RUNNING and row.worker_id in live_workers]
    queued = sorted((row.created_at, row.id, key) for key, row in rows.items()
                    if key in keys and key not in held
                    and row.status in (RunStatus.QUEUED, RunStatus.RUNNING))
    if any(left.get(key) is None for key in [*held, *(key for *_, key in queued)]):
        return "forecast: none yet (a run to come has no estimate)"
    return seeds_before_stop(spec.stop_after_hours, worked_s, len(live_workers),
                             [left[key] or 0.0 for key in held],
                             [(keys[key].seed, left[key] or 0.0) for *_, key in queued],
                             started_seeds(spec, rows, results))

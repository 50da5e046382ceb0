"""A spec's results folder read into tidy tables.

The grid comes from the `spec.toml` the runner stored there; each run's folder gives its state
and its CSV metrics. `runs` has one row per planned run (finished or not), `evals` and `rounds`
one row per line of the runs' eval.csv and rounds.csv, all keyed by `KEYS`. The budget is the
run's own `feedback.budget` (from its config.json; from the spec and presets if it never
started), so grids without a budgets axis still show each task's budget.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from experiments.spec import Spec, load_spec

KEYS = ["task", "variant", "eps", "budget", "seed"]
STATES = ("done", "stopped", "partial", "failed", "not started")


@dataclass(frozen=True)
class Results:
    spec: Spec
    folder: Path
    runs: pd.DataFrame
    """KEYS + algo, selection (feedback.selection), state, step (last reached), planned_steps,
    dir"""
    evals: pd.DataFrame
    """KEYS + eval.csv's columns (step, return, success_rate, ...)"""
    rounds: pd.DataFrame
    """KEYS + rounds.csv's columns (step, round, distinguishable_ratio, ...)"""


def _json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _last_step(csv_path: Path) -> int | None:
    """The `step` of the last row of a metrics CSV (its first column)."""
    try:
        lines = [line for line in csv_path.read_text().splitlines() if line.strip()]
    except OSError:
        return None
    try:
        return int(float(lines[-1].split(",", 1)[0])) if len(lines) > 1 else None
    except ValueError:
        return None


def run_state(folder: Path) -> tuple[str, int | None]:
    """(state, last step reached): done (done.json), failed (failed.json, the last attempt
    exited non-zero), stopped (stopped.json: an operator stopped it; it resumes when queued
    again), partial (a checkpoint or metrics, no marker: running or killed), or not started."""
    done = _json(folder / "done.json")
    step = _last_step(folder / "episodes.csv")
    if done is not None:
        return "done", done.get("step", step)
    if (folder / "failed.json").exists():
        return "failed", step
    if (folder / "stopped.json").exists():
        return "stopped", step
    if (folder / "checkpoint.pt").exists() or step is not None:
        return "partial", step
    return "not started", None


def read_metrics(path: Path) -> pd.DataFrame | None:
    """A run's metrics CSV by step, or None where it is missing, empty or has no step."""
    try:
        frame = pd.read_csv(path)
    except (FileNotFoundError, pd.errors.EmptyDataError):
        return None
    if frame.empty or "step" not in frame:
        return None
    # A resumed run rewrites rows after its checkpoint; keep one row per step, the last.
    return frame.drop_duplicates("step", keep="last").sort_values("step", kind="stable")


def load_results(folder: str | Path) -> Results:
    """Read `<results>/<spec name>` (the folder holding spec.toml)."""
    folder = Path(folder)
    spec = load_spec(folder / "spec.toml", check=False)
    runs: list[dict[str, Any]] = []
    evals: list[pd.DataFrame] = []
    rounds: list[pd.DataFrame] = []
    for run in spec.runs():
        path = folder / run.dir
        stored = _json(path / "config.json")
        feedback = stored["feedback"] if stored else vars(run.config().feedback)
        key = {"task": run.task, "variant": run.variant, "eps": run.eps,
               "budget": int(feedback["budget"]), "seed": run.seed}
        state, step = run_state(path)
        runs.append(key | {"algo": run.algo, "selection": feedback["selection"],
                           "state": state, "step": step, "planned_steps": run.steps,
                           "dir": str(run.dir)})
        for name, frames in (("eval.csv", evals), ("rounds.csv", rounds)):
            frame = read_metrics(path / name)
            if frame is not None:
                frames.append(frame.assign(**key)[KEYS + list(frame.columns)])
    table = pd.DataFrame(runs)
    # Keyed as the runs are, so that a grid without metrics yet still merges with its runs.
    empty = table[KEYS].iloc[:0].assign(step=pd.Series(dtype=float))
    return Results(spec, folder, table,
                   pd.concat(evals, ignore_index=True) if evals else empty,
                   pd.concat(rounds, ignore_index=True) if rounds else empty)

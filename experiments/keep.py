"""Keeping a grid's finished runs where its report is committed: `sepoa experiment keep SPEC
--out DIR` copies what `sepoa report` and the launcher read of each finished run (config.json,
done.json, the metric CSVs and the rest of its folder; labels gzipped) and the grid's
`spec.toml`, `sessions.csv` and `stop_rule.json`, and the skill quality measured beside each
snapshot the grid's runs start from (`snapshots/*.quality.json`, for the report's table; the
snapshots themselves stay behind). Checkpoints and TensorBoard files stay behind
(`experiments.carry.LEFT_BEHIND_WHEN_FINISHED`), so the folder is small enough to commit, and
hours of training are not lost with a machine.

DIR is itself a results folder of the grid: `sepoa report DIR` reads it. On another machine,
`cp -r DIR/. <results>/<spec name>/` puts the runs back (gunzip the labels where a tool reads
them); `sepoa experiment run` then counts each as finished and trains only the rest, and the
stop rule goes on counting from the sessions kept.
"""

from __future__ import annotations

import gzip
import shutil
from dataclasses import dataclass
from pathlib import Path

from experiments.carry import LEFT_BEHIND_WHEN_FINISHED
from experiments.sessions import FILE as SESSIONS
from experiments.sessions import worked
from experiments.skill_quality import snapshots_quality_files
from experiments.spec import Spec, grid_snapshots
from experiments.stop_rule import FILE as STOP_RULE

GRID_FILES = ("spec.toml", SESSIONS, STOP_RULE)
"""the grid's own files, beside its runs"""
GZIPPED = (".jsonl",)
"""files kept gzipped (labels: the largest a finished run has)"""


@dataclass(frozen=True)
class Kept:
    runs: int
    """finished runs copied"""
    unfinished: int
    """the spec's other runs, left out"""
    size: int
    """bytes written"""
    running: bool
    """the grid's last session was still running: its sessions.csv row has no end yet"""


def keep(spec: Spec, results: Path, out: Path) -> Kept:
    """Copy the finished runs of `spec` in `results` and the grid's files into `out`; a run
    kept before is copied again (a finished run's files do not change)."""
    folder = results / spec.name
    if not (folder / "spec.toml").exists():
        raise ValueError(f"{folder} holds no grid (no spec.toml): nothing of {spec.name} "
                         f"was run with --results {results}")
    out.mkdir(parents=True, exist_ok=True)
    size = sum(_copy(folder / name, out / name) for name in GRID_FILES
               if (folder / name).exists())
    runs = unfinished = 0
    for run in spec.runs():
        source = folder / run.dir
        if not (source / "done.json").exists():
            unfinished += 1
            continue
        runs += 1
        for path in sorted(source.rglob("*")):
            parts = path.relative_to(source).parts
            if path.is_file() and parts[0] not in LEFT_BEHIND_WHEN_FINISHED:
                size += _copy(path, out / run.dir / Path(*parts))
    for path in snapshots_quality_files(grid_snapshots(spec), [results / "snapshots"]):
        size += _copy(path, out / "snapshots" / path.name)
    period = worked(folder)
    return Kept(runs, unfinished, size, period is not None and period.running_since is not None)


def _copy(source: Path, target: Path) -> int:
    """Copy one file (gzipped where `GZIPPED` says, `.gz` added); the bytes written."""
    target.parent.mkdir(parents=True, exist_ok=True)
    if source.suffix in GZIPPED:
        target = target.with_name(target.name + ".gz")
        # No time or name in the header: the same labels give the same bytes to commit.
        with source.open("rb") as raw, target.open("wb") as file, \
                gzip.GzipFile(filename="", mode="wb", fileobj=file, mtime=0) as packed:
            shutil.copyfileobj(raw, packed)
    else:
        shutil.copyfile(source, target)
    return target.stat().st_size

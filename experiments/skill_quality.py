"""The skill quality of a results folder's snapshots, for reports: what `sepoa pretrain` wrote
beside each snapshot (`trainer/skills/quality.py`, `<snapshot>.quality.json`), read without
torch, with 95 % bootstrap intervals of the top-5 means over the measured episodes."""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from runvocab.snapshot_names import QUALITY_FORMAT, quality_path

TOP = 5
COLUMNS = ["snapshot", "task", "seed", "steps", "skills", "skill_median", "skill_top5",
           "skill_top5_low", "skill_top5_high", "skill_max", "random_median", "random_top5",
           "random_top5_low", "random_top5_high", "random_max"]


def quality_files(folder: Path) -> list[Path]:
    """The quality files in `folder` (a snapshots folder), by name."""
    return sorted(folder.glob("*.quality.json")) if folder.is_dir() else []


def snapshots_quality_files(snapshots: Iterable[str], folders: Sequence[Path]) -> list[Path]:
    """The quality files of the snapshots named, by name, each from the first of `folders`
    that holds it (a snapshot measured nowhere is left out)."""
    found = []
    for name in sorted({os.path.basename(quality_path(s)) for s in snapshots}):
        held = next((folder / name for folder in folders if (folder / name).is_file()), None)
        if held is not None:
            found.append(held)
    return found


def bootstrap_top(returns: list[float], resamples: int, rng: np.random.Generator,
                  ) -> tuple[float, float, float]:
    """The top-5 mean of `returns` and its 95 % percentile-bootstrap interval."""
    values = np.asarray(returns, dtype=np.float64)
    draws = rng.choice(values, size=(resamples, len(values)), replace=True)
    tops = np.sort(draws, axis=1)[:, -TOP:].mean(axis=1)
    low, high = np.percentile(tops, [2.5, 97.5])
    return float(np.sort(values)[-TOP:].mean()), float(low), float(high)


def requested_steps(data: dict[str, Any]) -> int:
    """The pretraining length a snapshot stands for: the step it was asked at (an intermediate
    snapshot, `-at<step>` in its name) or its pretraining's length."""
    name = data["snapshot"]
    if "-at" in name:
        return int(name.rsplit("-at", 1)[1].split(".")[0])
    return int(data["pretrain_steps"])


def quality_table(files: Iterable[Path], resamples: int = 10_000) -> pd.DataFrame:
    """One row per measured snapshot of the quality `files`, ordered by task, length and
    seed. Each snapshot's bootstrap has a stream of its own (from its seed and length), so its
    intervals do not move as other snapshots join the table."""
    rows = []
    for path in files:
        data = json.loads(path.read_text())
        if data.get("format") != QUALITY_FORMAT:
            continue
        rng = np.random.default_rng([data["seed"], requested_steps(data)])
        skill = bootstrap_top(data["skill_returns"], resamples, rng)
        rand = bootstrap_top(data["random_action_returns"], resamples, rng)
        rows.append({
            "snapshot": data["snapshot"], "task": data["task"], "seed": data["seed"],
            "steps": requested_steps(data), "skills": data["skills"],
            "skill_median": data["skill"]["median"], "skill_top5": skill[0],
            "skill_top5_low": skill[1], "skill_top5_high": skill[2],
            "skill_max": data["skill"]["max"], "random_median": data["random_actions"]["median"],
            "random_top5": rand[0], "random_top5_low": rand[1], "random_top5_high": rand[2],
            "random_max": data["random_actions"]["max"],
        })
    table = pd.DataFrame(rows, columns=COLUMNS)
    return table.sort_values(["task", "steps", "seed"], kind="stable").reset_index(drop=True)


def quality_markdown(table: pd.DataFrame) -> str:
    header = ("| task | steps | seed | skills: median | skills: top-5 mean [95 %] | skills: max "
              "| random: median | random: top-5 mean [95 %] | random: max |\n"
              "|---|---:|---:|---:|---|---:|---:|---|---:|")
    rows = [f"| {r.task} | {r.steps:,} | {r.seed} | {r.skill_median:.1f} | {r.skill_top5:.1f} "
            f"[{r.skill_top5_low:.1f}, {r.skill_top5_high:.1f}] | {r.skill_max:.1f} | "
            f"{r.random_median:.1f} | {r.random_top5:.1f} [{r.random_top5_low:.1f}, "
            f"{r.random_top5_high:.1f}] | {r.random_max:.1f} |" for r in table.itertuples()]
    return "\n".join([header, *rows])

"""How each arm's agent trained, from its runs' episodes.csv: at a quarter, half, three
quarters and all of the spec's steps, the updates made so far and, over the episodes of the
last `WINDOW_STEPS` before that point, the mean training return and the mean of the last
update's α, Q (the critics' mean estimate on its batch) and critic loss, as each episode's row
logs them. A reader sees what the agent did, not only what it scored: a late start, a
temperature that collapsed, value estimates that lag.

Per cell and point: mean ± sample std across the seeds that reached the point (finished or
not); a run short of a point is left out of it, and an episode row without α, Q or critic loss
(no update yet) is left out of that column's window.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import pandas as pd

from experiments.results import KEYS, Results, read_metrics
from experiments.tables import cell, grid_cells, markdown_table, mean_std

POINTS = (0.25, 0.5, 0.75, 1.0)
"""the points, as fractions of the spec's steps"""
WINDOW_STEPS = 5000
"""the span before a point whose episodes are averaged (5 episodes of 1 000 steps)"""
COLUMNS = {"updates": ("updates", 0), "return": ("training return", 1),
           "alpha": ("α", 4), "q": ("Q", 2), "critic_loss": ("critic loss", 3)}
"""episodes.csv column -> its Markdown header and decimals"""
DOC = (
    "From each run's episodes.csv, at a quarter, half, three quarters and all of the spec's "
    f"steps: the updates made by then, and over the episodes of the last {WINDOW_STEPS:,} steps "
    "before the point the mean training-episode return and the mean of the last update's α "
    "(the entropy temperature), Q (the critics' mean estimate on that update's batch) and "
    "critic loss. The SAC oracle trains on the true reward and S-EPOA on r̂ (or on the true "
    "reward with `reward.true_reward`), so their Q are on different scales unless both use the "
    "true reward. Mean ± sample std across the seeds that reached the point, finished or not.")


def agent_per_run(results: Results) -> pd.DataFrame:
    """KEYS + point (the step) + COLUMNS: one row per run and point it reached."""
    rows: list[dict[str, Any]] = []
    for run in results.runs.itertuples():
        episodes = read_metrics(results.folder / run.dir / "episodes.csv")
        if episodes is None:
            continue
        key = {k: getattr(run, k) for k in KEYS}
        for fraction in POINTS:
            point = round(fraction * run.planned_steps)
            if episodes["step"].iloc[-1] < point:
                break
            before = episodes[episodes["step"] <= point]
            window = before[before["step"] > point - WINDOW_STEPS]
            row = key | {"point": point}
            for column in COLUMNS:  # a column older runs lack is NaN
                if column not in episodes or before.empty:  # no episode ended by the point
                    row[column] = math.nan
                elif column == "updates":
                    row[column] = before[column].iloc[-1]
                else:
                    values = window[column]
                    row[column] = values.mean() if values.notna().any() else math.nan
            rows.append(row)
    return pd.DataFrame(rows, columns=[*KEYS, "point", *COLUMNS])


def agent_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget, variant and point: mean and std across seeds of each of COLUMNS
    (`<column>_mean`, `<column>_std`, and `<column>_n` the seeds with a value), and the seeds
    that reached the point (`n`)."""
    per_run = agent_per_run(results)
    rows = []
    for cell_key, sub in grid_cells(results.runs, results):
        seeds = per_run.merge(sub[KEYS], on=KEYS)
        for point, at in seeds.groupby("point", sort=True):
            row = cell_key | {"point": int(point), "n": len(at)}
            for column in COLUMNS:
                mean, std, n = mean_std(at[column])
                row |= {f"{column}_mean": mean, f"{column}_std": std, f"{column}_n": n}
            rows.append(row)
    return pd.DataFrame(rows)


def agent_markdown(table: pd.DataFrame, seeds: Mapping[str, int]) -> str:
    """The table in Markdown; `(n=k)` below the variant's planned `seeds`."""
    if table.empty:
        return "No run has logged an episode yet."
    header = ["task", "eps", "budget", "variant", "step"] + [h for h, _ in COLUMNS.values()]
    rows = [[r["task"], f"{r['eps']:g}", str(r["budget"]), r["variant"], f"{r['point']:,}"]
            + [cell(r[f"{c}_mean"], r[f"{c}_std"], r[f"{c}_n"], digits, seeds[r["variant"]])
               for c, (_, digits) in COLUMNS.items()]
            for _, r in table.iterrows()]
    return markdown_table(header, rows)

"""The report's tables: each run's numbers, and per cell of the grid their mean across seeds,
as data frames and as Markdown.

The numbers, exactly (docs/EXPERIMENTS.md says the same):
- Across seeds, "mean ± std" is the mean and the sample standard deviation (ddof=1); with one
  seed there is no std and the cell shows the mean alone. A cell with fewer seeds than its
  variant plans (its own seeds, else the spec's) says `(n=k)`.
- Final return of a run: the `return` of the last row of its eval.csv (itself the mean over
  that evaluation's episodes), for finished runs only (done.json); unfinished runs are counted
  and listed with the step of their last evaluation, never averaged in.
- Distinguishability of a run: the mean of rounds.csv `distinguishable_ratio` over every round
  after the first (the first round is uniform for every method); runs with fewer than two
  rounds are left out; unfinished runs count with the rounds they have.
- Same-agent distinguishability (runs with rounds.csv `compare_distinguishable_ratio`): per run
  the means of its own `distinguishable_ratio` and of the compared rule's ratio over the same
  rounds, those after the first where the compared ratio is logged.
- Round diagnostics: per run the mean `reward_corr` over all rounds and its last round's, and
  the means of `max_trajectory_share` and `trajectory_pairs` (and S-EPOA's `task_skill_cosine`
  and `task_skill_gain`) over the rounds after the first.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import numpy as np
import pandas as pd

from experiments.results import KEYS, Results

GROUP = ["task", "eps", "budget"]


def mean_std(values: Iterable[float]) -> tuple[float, float, int]:
    """(mean, sample std (ddof=1; NaN below two values), count) of the finite values."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=float)
    if not len(v):
        return math.nan, math.nan, 0
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else math.nan, len(v)


def cell(mean: float, std: float, n: int, digits: int, planned: int) -> str:
    """'mean ± std' with fixed decimals; '–' without values; '(n=k)' below the planned seeds."""
    if n == 0 or not math.isfinite(mean):
        return "–"
    text = f"{mean:.{digits}f}"
    if n > 1:
        text += f" ± {std:.{digits}f}"
    return text + (f" (n={n})" if n < planned else "")


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def variant_labels(results: Results) -> list[str]:
    return [v.label for v in results.spec.variants]


def _title(task: str, eps: float, budget: int) -> str:
    return f"{task}, eps {eps:g}, budget {budget}"


def _join(runs: pd.DataFrame, per_run: pd.DataFrame, columns: list[str]) -> pd.DataFrame:
    """`runs` with `columns` of `per_run` (one row per run, keyed by KEYS); NaN where absent."""
    have = [c for c in columns if c in per_run]
    out = runs.merge(per_run[KEYS + have], on=KEYS, how="left") if len(per_run) else runs.copy()
    for col in columns:
        if col not in out:
            out[col] = math.nan
    return out


def grid_cells(runs: pd.DataFrame, results: Results
               ) -> Iterator[tuple[dict[str, Any], pd.DataFrame]]:
    """A table's cells: per task, eps and budget, each variant's runs (variants in the spec's
    order, those without runs there left out), with the cell's key columns."""
    for (task, eps, budget), group in runs.groupby(GROUP, sort=False):
        for variant in variant_labels(results):
            sub = group[group["variant"] == variant]
            if not sub.empty:
                yield {"task": task, "eps": eps, "budget": budget, "variant": variant}, sub


def final_returns(results: Results) -> pd.DataFrame:
    """One row per planned run: its state and last evaluation (step, return, success rate)."""
    last = results.evals.drop_duplicates(KEYS, keep="last").rename(
        columns={"step": "eval_step", "return": "final_return", "success_rate": "final_success"})
    return _join(results.runs, last, ["eval_step", "final_return", "final_success"])


def final_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget and variant: final return (and success rate) over finished seeds
    (`n`: those with an evaluation), with how many seeds finished of those planned, and the
    unfinished ones' last evaluation."""
    rows = []
    for cell_key, sub in grid_cells(final_returns(results), results):
        done = sub[sub["state"] == "done"]
        r_mean, r_std, n = mean_std(done["final_return"])
        s_mean, s_std, _ = mean_std(done["final_success"])
        unfinished = ", ".join(
            [f"s{r.seed} {r.state}" + ("" if pd.isna(r.eval_step) else f" @ {r.eval_step:g}")
             for r in sub[sub["state"] != "done"].itertuples()]
            + [f"s{r.seed} done, no evaluation"
               for r in done[~np.isfinite(done["final_return"].astype(float))].itertuples()])
        rows.append(cell_key | {"algo": sub["algo"].iloc[0], "return_mean": r_mean,
                                "return_std": r_std, "n": n, "finished": len(done),
                                "planned": len(sub),
                                "success_mean": s_mean, "success_std": s_std,
                                "unfinished": unfinished})
    return pd.DataFrame(rows)


def _run_rounds(results: Results) -> Iterator[tuple[dict[str, Any], pd.DataFrame]]:
    """Each run's key and its rounds in step order; `.iloc[1:]` is the rounds after the first
    (the first is uniform for every method)."""
    for key, group in results.rounds.groupby(KEYS, sort=False):
        yield dict(zip(KEYS, key, strict=True)), group.sort_values("step", kind="stable")


def distinguishability_per_run(results: Results) -> pd.DataFrame:
    """KEYS + `distinguishability`: a run's mean ratio over its rounds after the first."""
    rows = []
    if "distinguishable_ratio" in results.rounds:
        for key, rounds in _run_rounds(results):
            later = rounds.iloc[1:]
            if len(later):
                rows.append(key | {"distinguishability": later["distinguishable_ratio"].mean()})
    return pd.DataFrame(rows, columns=[*KEYS, "distinguishability"])


def distinguishability_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget and query-selecting variant (algo not sac): mean ± std across
    seeds of each run's distinguishability, with the variant's selection rule."""
    runs = results.runs[results.runs["algo"] != "sac"]
    runs = _join(runs, distinguishability_per_run(results), ["distinguishability"])
    rows = []
    for cell_key, sub in grid_cells(runs, results):
        mean, std, n = mean_std(sub["distinguishability"])
        rows.append(cell_key | {"algo": sub["algo"].iloc[0],
                                "selection": "/".join(sorted(set(sub["selection"]))),
                                "mean": mean, "std": std, "n": n, "planned": len(sub)})
    return pd.DataFrame(rows)


def _run_config(results: Results, run_dir: str) -> dict[str, Any]:
    """A run's stored config.json ({} if it has none)."""
    try:
        return json.loads((results.folder / run_dir / "config.json").read_text())
    except (OSError, ValueError):
        return {}


def same_agent_per_run(results: Results) -> pd.DataFrame:
    """KEYS + `own`, `compared`, `rounds`: a run's mean distinguishable ratio of its own picks
    and of `feedback.compare_rule`'s picks over the same rounds (after the first, with the
    compared ratio logged)."""
    columns = [*KEYS, "own", "compared", "rounds"]
    if "compare_distinguishable_ratio" not in results.rounds:
        return pd.DataFrame(columns=columns)
    rows = []
    for key, rounds in _run_rounds(results):
        later = rounds.iloc[1:]
        later = later[later["compare_distinguishable_ratio"].notna()]
        if len(later):
            rows.append(key | {"own": later["distinguishable_ratio"].mean(),
                               "compared": later["compare_distinguishable_ratio"].mean(),
                               "rounds": len(later)})
    return pd.DataFrame(rows, columns=columns)


def same_agent_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget and variant with a compared rule: mean ± std across seeds of the
    own and the compared rule's distinguishability on the same agent, pool and reward model."""
    runs = _join(results.runs, same_agent_per_run(results), ["own", "compared"])
    rows = []
    for cell_key, sub in grid_cells(runs, results):
        own, own_std, n = mean_std(sub["own"])
        if n == 0:
            continue
        compared, compared_std, _ = mean_std(sub["compared"])
        rules = {_run_config(results, d).get("feedback", {}).get("compare_rule", "")
                 for d in sub["dir"]}
        rows.append(cell_key | {"algo": sub["algo"].iloc[0],
                                "selection": "/".join(sorted(set(sub["selection"]))),
                                "compare_rule": "/".join(sorted(rules - {""})) or "?",
                                "own_mean": own, "own_std": own_std,
                                "compared_mean": compared, "compared_std": compared_std,
                                "n": n})
    return pd.DataFrame(rows)


DIAGNOSTICS = {
    "reward_corr_mean": "reward_corr",
    "reward_corr_last": "reward_corr",
    "max_trajectory_share": "max_trajectory_share",
    "trajectory_pairs": "trajectory_pairs",
    "task_skill_cosine": "task_skill_cosine",
    "task_skill_gain": "task_skill_gain",
}
"""round-diagnostics column -> the rounds.csv column it comes from"""
AFTER_FIRST_ROUND = ("max_trajectory_share", "trajectory_pairs", "task_skill_cosine",
                     "task_skill_gain")
"""diagnostics averaged over the rounds after the first (where the first has no meaning: its
queries are uniform, and z_task has no predecessor)"""


def diagnostics_per_run(results: Results) -> pd.DataFrame:
    """KEYS + DIAGNOSTICS, those whose rounds.csv column exists: a run's mean `reward_corr`
    over all rounds and its last round's, and the means of `AFTER_FIRST_ROUND` over the
    rounds after the first."""
    have = [c for c, source in DIAGNOSTICS.items() if source in results.rounds]
    rows = []
    for key, rounds in _run_rounds(results):
        row = dict(key)
        if "reward_corr" in rounds:
            row |= {"reward_corr_mean": rounds["reward_corr"].mean(),
                    "reward_corr_last": rounds["reward_corr"].iloc[-1]}
        for col in AFTER_FIRST_ROUND:
            if col in rounds:
                row[col] = rounds[col].iloc[1:].mean() if len(rounds) > 1 else math.nan
        rows.append(row)
    return pd.DataFrame(rows, columns=[*KEYS, *have])


def diagnostics_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget and query-selecting variant: mean ± std across seeds of each
    diagnostic of `diagnostics_per_run` (`<name>_mean`, `<name>_std`) and the seeds with
    rounds."""
    per_run = diagnostics_per_run(results)
    have = [c for c in DIAGNOSTICS if c in per_run]
    runs = _join(results.runs[results.runs["algo"] != "sac"], per_run, have)
    rows = []
    for cell_key, sub in grid_cells(runs, results):
        row = cell_key | {"algo": sub["algo"].iloc[0]}
        for col in have:
            mean, std, _ = mean_std(sub[col])
            row |= {f"{col}_mean": mean, f"{col}_std": std}
        rows.append(row | {"n": int(sub[have].notna().any(axis=1).sum())})
    return pd.DataFrame(rows)


def final_markdown(table: pd.DataFrame, metaworld: bool) -> str:
    parts = []
    for (task, eps, budget), group in table.groupby(GROUP, sort=False):
        header = ["variant", "algo", "final return"] + (["success rate"] if metaworld else [])
        header += ["seeds finished", "unfinished (state @ last evaluation step)"]
        rows = []
        for r in group.itertuples():
            # `(n=k)` where a finished run has no final return to average.
            row = [r.variant, r.algo, cell(r.return_mean, r.return_std, r.n, 1, r.finished)]
            if metaworld:
                row.append(cell(r.success_mean, r.success_std, r.n, 2, r.finished))
            rows.append(row + [f"{r.finished}/{r.planned}", r.unfinished or "–"])
        parts.append(f"### {_title(task, eps, budget)}\n\n{markdown_table(header, rows)}")
    return "\n\n".join(parts) if parts else "No runs."


def queries_markdown(table: pd.DataFrame, variants: list[str], seeds: Mapping[str, int]
                     ) -> str:
    """Per task and eps: a row per budget, a column per variant, final return cells (`(n=k)`
    below the variant's planned `seeds`)."""
    parts = []
    for (task, eps), group in table.groupby(["task", "eps"], sort=False):
        present = [v for v in variants if v in set(group["variant"])]
        rows = []
        for budget, by_budget in group.groupby("budget", sort=True):
            cells = {r.variant: cell(r.return_mean, r.return_std, r.n, 1, seeds[r.variant])
                     for r in by_budget.itertuples()}
            rows.append([str(budget)] + [cells.get(v, "–") for v in present])
        parts.append(f"### {task}, eps {eps:g}\n\n" + markdown_table(["queries", *present], rows))
    return "\n\n".join(parts) if parts else "No runs."


def distinguishability_markdown(table: pd.DataFrame, seeds: Mapping[str, int]) -> str:
    if table.empty:
        return "No variant selects queries (only sac runs)."
    variants = list(dict.fromkeys(table["variant"]))
    rules = {r.variant: r.selection for r in table.itertuples()}
    header = ["task", "eps", "budget"] + [f"{v} ({rules[v]})" for v in variants]
    rows = []
    for (task, eps, budget), group in table.groupby(GROUP, sort=False):
        cells = {r.variant: cell(r.mean, r.std, r.n, 3, seeds[r.variant])
                 for r in group.itertuples()}
        rows.append([task, f"{eps:g}", str(budget)] + [cells.get(v, "–") for v in variants])
    return markdown_table(header, rows)


def same_agent_markdown(table: pd.DataFrame, seeds: Mapping[str, int]) -> str:
    header = ["task", "eps", "budget", "variant", "rule", "distinguishable", "compared rule",
              "distinguishable (compared)"]
    rows = [[r.task, f"{r.eps:g}", str(r.budget), r.variant, r.selection,
             cell(r.own_mean, r.own_std, r.n, 3, seeds[r.variant]), r.compare_rule,
             cell(r.compared_mean, r.compared_std, r.n, 3, seeds[r.variant])]
            for r in table.itertuples()]
    return markdown_table(header, rows)


DIAGNOSTICS_HEADER = {"reward_corr_mean": ("reward corr (mean over rounds)", 3),
                      "reward_corr_last": ("reward corr (last round)", 3),
                      "max_trajectory_share": ("max trajectory share", 3),
                      "trajectory_pairs": ("trajectory pairs", 1),
                      "task_skill_cosine": ("z_task cosine to the round before", 3),
                      "task_skill_gain": ("R_θ gain of the new z_task", 2)}
"""diagnostic -> its Markdown column header and decimals"""


def diagnostics_markdown(table: pd.DataFrame, seeds: Mapping[str, int]) -> str:
    if table.empty:
        return "No variant selects queries (only sac runs)."
    have = [c for c in DIAGNOSTICS_HEADER if f"{c}_mean" in table]
    header = ["task", "eps", "budget", "variant"] + [DIAGNOSTICS_HEADER[c][0] for c in have]
    rows = [[r["task"], f"{r['eps']:g}", str(r["budget"]), r["variant"]]
            + [cell(r[f"{c}_mean"], r[f"{c}_std"], r["n"], DIAGNOSTICS_HEADER[c][1],
                    seeds[r["variant"]])
               for c in have]
            for _, r in table.iterrows()]
    return markdown_table(header, rows)

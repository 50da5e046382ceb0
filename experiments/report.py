"""A spec's report: learning-curve figures and Markdown + CSV tables, indexed by report.md.

The numbers, exactly (docs/EXPERIMENTS.md says the same):
- Across seeds, "mean ± std" is the mean and the sample standard deviation (ddof=1); with one
  seed there is no std and the cell shows the mean alone. A cell with fewer seeds than the
  spec plans says `(n=k)`.
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
- Proposition 1: Monte Carlo Var[P] against the return gap, and the measured curve of one
  finished, checkpointed run per query-selecting variant (its lowest seed); see proposition.py.
- Curves: see `plots.align` (common step range of the seeds with at least one evaluation,
  linear interpolation, mean ± one sample std).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from experiments import preregistered
from experiments.proposition import (
    measured_disagreement,
    proposition_png,
    simulated_disagreement,
)
from experiments.results import KEYS, STATES, Results, load_results
from experiments.skill_quality import quality_markdown, quality_table
from experiments.spec import METRICS
from figures.curves import Band, align, grid_png

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


def _markdown(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def _variants(results: Results) -> list[str]:
    return [v.label for v in results.spec.variants]


def _title(task: str, eps: float, budget: int) -> str:
    return f"{task}, eps {eps:g}, budget {budget}"


# ---------------------------------------------------------------------------------------------
# Tables.

def _join(runs: pd.DataFrame, per_run: pd.DataFrame, columns: list[str]) -> pd.DataFrame:
    """`runs` with `columns` of `per_run` (one row per run, keyed by KEYS); NaN where absent."""
    have = [c for c in columns if c in per_run]
    out = runs.merge(per_run[KEYS + have], on=KEYS, how="left") if len(per_run) else runs.copy()
    for col in columns:
        if col not in out:
            out[col] = math.nan
    return out


def _cells(runs: pd.DataFrame, results: Results) -> Iterator[tuple[dict[str, Any], pd.DataFrame]]:
    """A table's cells: per task, eps and budget, each variant's runs (variants in the spec's
    order, those without runs there left out), with the cell's key columns."""
    for (task, eps, budget), group in runs.groupby(GROUP, sort=False):
        for variant in _variants(results):
            sub = group[group["variant"] == variant]
            if not sub.empty:
                yield {"task": task, "eps": eps, "budget": budget, "variant": variant}, sub


def final_returns(results: Results) -> pd.DataFrame:
    """One row per planned run: its state and last evaluation (step, return, success rate)."""
    last = results.evals.drop_duplicates(KEYS, keep="last").rename(
        columns={"step": "eval_step", "return": "final_return", "success_rate": "final_success"})
    return _join(results.runs, last, ["eval_step", "final_return", "final_success"])


def final_table(results: Results) -> pd.DataFrame:
    """Per task, eps, budget and variant: final return (and success rate) over finished seeds,
    with how many seeds finished of those planned, and the unfinished ones' last evaluation."""
    rows = []
    for cell_key, sub in _cells(final_returns(results), results):
        done = sub[sub["state"] == "done"]
        r_mean, r_std, n = mean_std(done["final_return"])
        s_mean, s_std, _ = mean_std(done["final_success"])
        unfinished = ", ".join(
            f"s{r.seed} {r.state}" + ("" if pd.isna(r.eval_step) else f" @ {r.eval_step:g}")
            for r in sub[sub["state"] != "done"].itertuples())
        rows.append(cell_key | {"algo": sub["algo"].iloc[0], "return_mean": r_mean,
                                "return_std": r_std, "n": n, "planned": len(sub),
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
    for cell_key, sub in _cells(runs, results):
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
    for cell_key, sub in _cells(runs, results):
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
    for cell_key, sub in _cells(runs, results):
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
            row = [r.variant, r.algo, cell(r.return_mean, r.return_std, r.n, 1, r.n)]
            if metaworld:
                row.append(cell(r.success_mean, r.success_std, r.n, 2, r.n))
            rows.append(row + [f"{r.n}/{r.planned}", r.unfinished or "–"])
        parts.append(f"### {_title(task, eps, budget)}\n\n{_markdown(header, rows)}")
    return "\n\n".join(parts) if parts else "No runs."


def queries_markdown(table: pd.DataFrame, variants: list[str], seeds: int) -> str:
    """Per task and eps: a row per budget, a column per variant, final return cells."""
    parts = []
    for (task, eps), group in table.groupby(["task", "eps"], sort=False):
        present = [v for v in variants if v in set(group["variant"])]
        rows = []
        for budget, by_budget in group.groupby("budget", sort=True):
            cells = {r.variant: cell(r.return_mean, r.return_std, r.n, 1, seeds)
                     for r in by_budget.itertuples()}
            rows.append([str(budget)] + [cells.get(v, "–") for v in present])
        parts.append(f"### {task}, eps {eps:g}\n\n" + _markdown(["queries", *present], rows))
    return "\n\n".join(parts) if parts else "No runs."


def distinguishability_markdown(table: pd.DataFrame, seeds: int) -> str:
    if table.empty:
        return "No variant selects queries (only sac runs)."
    variants = list(dict.fromkeys(table["variant"]))
    rules = {r.variant: r.selection for r in table.itertuples()}
    header = ["task", "eps", "budget"] + [f"{v} ({rules[v]})" for v in variants]
    rows = []
    for (task, eps, budget), group in table.groupby(GROUP, sort=False):
        cells = {r.variant: cell(r.mean, r.std, r.n, 3, seeds) for r in group.itertuples()}
        rows.append([task, f"{eps:g}", str(budget)] + [cells.get(v, "–") for v in variants])
    return _markdown(header, rows)


def same_agent_markdown(table: pd.DataFrame, seeds: int) -> str:
    header = ["task", "eps", "budget", "variant", "rule", "distinguishable", "compared rule",
              "distinguishable (compared)"]
    rows = [[r.task, f"{r.eps:g}", str(r.budget), r.variant, r.selection,
             cell(r.own_mean, r.own_std, r.n, 3, seeds), r.compare_rule,
             cell(r.compared_mean, r.compared_std, r.n, 3, seeds)] for r in table.itertuples()]
    return _markdown(header, rows)


DIAGNOSTICS_HEADER = {"reward_corr_mean": ("reward corr (mean over rounds)", 3),
                      "reward_corr_last": ("reward corr (last round)", 3),
                      "max_trajectory_share": ("max trajectory share", 3),
                      "trajectory_pairs": ("trajectory pairs", 1),
                      "task_skill_cosine": ("z_task cosine to the round before", 3),
                      "task_skill_gain": ("R_θ gain of the new z_task", 2)}
"""diagnostic -> its Markdown column header and decimals"""


def diagnostics_markdown(table: pd.DataFrame, seeds: int) -> str:
    if table.empty:
        return "No variant selects queries (only sac runs)."
    have = [c for c in DIAGNOSTICS_HEADER if f"{c}_mean" in table]
    header = ["task", "eps", "budget", "variant"] + [DIAGNOSTICS_HEADER[c][0] for c in have]
    rows = [[r["task"], f"{r['eps']:g}", str(r["budget"]), r["variant"]]
            + [cell(r[f"{c}_mean"], r[f"{c}_std"], r["n"], DIAGNOSTICS_HEADER[c][1], seeds)
               for c in have]
            for _, r in table.iterrows()]
    return _markdown(header, rows)


# ---------------------------------------------------------------------------------------------
# Proposition 1.

PROPOSITION_C = (0.25, 1.0, 4.0)
PROPOSITION_GAPS = np.linspace(0.0, 6.0, 25)


def proposition_runs(results: Results) -> pd.DataFrame:
    """The runs whose ensemble the Proposition 1 figure measures: finished, query-selecting,
    with a checkpoint.pt; the lowest seed of each variant."""
    runs = results.runs[(results.runs["state"] == "done") & (results.runs["algo"] != "sac")]
    # A boolean Series, not a list: an empty list would select no columns of an empty frame.
    kept = pd.Series([(results.folder / d / "checkpoint.pt").exists() for d in runs["dir"]],
                     index=runs.index, dtype=bool)
    runs = runs[kept]
    return runs.sort_values("seed", kind="stable").drop_duplicates("variant")


def proposition_section(results: Results, out: Path,
                        pairs: int = 20_000) -> tuple[pd.DataFrame, str]:
    """Write proposition1.png; the per-run table (KEYS, pairs, spearman) and the section's
    Markdown body."""
    simulated = {c: (PROPOSITION_GAPS, simulated_disagreement(
        PROPOSITION_GAPS, c, samples=100_000, rng=np.random.default_rng(0)))
        for c in PROPOSITION_C}
    measured, rows, failed = {}, [], []
    for run in proposition_runs(results).itertuples():
        try:
            curve = measured_disagreement(results.folder / run.dir, pairs=pairs)
        except (OSError, KeyError, ValueError, RuntimeError) as err:
            failed.append(f"- {run.dir}: {type(err).__name__}: {err}")
            continue
        measured[f"{run.variant} s{run.seed}"] = curve.table
        rows.append({k: getattr(run, k) for k in KEYS}
                    | {"pairs": int(curve.table["pairs"].sum()), "spearman": curve.spearman})
    (out / "proposition1.png").write_bytes(proposition_png(simulated, measured))
    table = pd.DataFrame(rows, columns=[*KEYS, "pairs", "spearman"])
    body = ["![Proposition 1](proposition1.png)", ""]
    if len(table):
        body.append(_markdown(
            ["variant", "task", "eps", "budget", "seed", "pairs", "Spearman(gap, Var[P])"],
            [[r.variant, r.task, f"{r.eps:g}", str(r.budget), str(r.seed), str(r.pairs),
              f"{r.spearman:.3f}"] for r in table.itertuples()]))
    else:
        body.append("No finished query-selecting run with a checkpoint.pt: Monte Carlo only.")
    if failed:
        body += ["", "Runs that could not be measured:", "", *failed]
    return table, "\n".join(body)


# ---------------------------------------------------------------------------------------------
# Figures.

def curve_panels(results: Results, metric: str, tasks: list[str],
                 budget: int | None) -> dict[tuple[str, str], dict[str, Band]]:
    """{(f"eps {e}", task): {variant: Band}} of `metric` from eval.csv; one budget or all."""
    evals = results.evals
    if budget is not None:
        evals = evals[evals["budget"] == budget]
    panels: dict[tuple[str, str], dict[str, Band]] = {}
    for eps in results.spec.eps:
        for task in tasks:
            curves = {}
            for variant in _variants(results):
                sub = evals[(evals["task"] == task) & (evals["eps"] == eps)
                            & (evals["variant"] == variant)]
                if sub.empty or metric not in sub:
                    continue
                seeds = [(g["step"].to_numpy(), g[metric].to_numpy())
                         for _, g in sub.groupby("seed", sort=True)]
                curves[variant] = align(seeds)
            panels[(f"eps {eps:g}", task)] = curves
    return panels


def write_figures(results: Results, out: Path) -> list[tuple[str, str, dict]]:
    """Write the curve figures; (file name, caption, panels) of each."""
    spec = results.spec
    base = "ablation" if spec.kind == "ablation" else "curves"
    budgets: list[int | None] = list(spec.budgets) if len(spec.budgets) > 1 else [None]
    rows = [f"eps {e:g}" for e in spec.eps]
    metaworld = [t for t in spec.tasks if t.startswith("metaworld:")]
    written = []
    for budget in budgets:
        suffix = "" if budget is None else f"_budget{budget}"
        title = spec.title + ("" if budget is None else f", {budget} queries")
        figures = [(f"{base}{suffix}.png", "evaluation return", "return", list(spec.tasks))]
        if metaworld:
            figures.append((f"success{suffix}.png", "evaluation success rate",
                            "success_rate", metaworld))
        for name, ylabel, metric, tasks in figures:
            panels = curve_panels(results, metric, tasks, budget)
            (out / name).write_bytes(grid_png(panels, rows, tasks, title=title, ylabel=ylabel))
            written.append((name, f"{ylabel}{'' if budget is None else f', {budget} queries'}",
                            panels))
    return written


def _short_curves(panels: dict[tuple[str, str], dict[str, Band]], seeds: int,
                  steps: int) -> list[str]:
    """Curves with fewer seeds than planned, or that stop before the spec's steps."""
    return [f"{col}, {row}: {label}: {band.n} of {seeds} seeds"
            + (f", up to step {band.steps[-1]:g}" if len(band.steps) else ", no evaluation")
            for (row, col), curves in panels.items() for label, band in curves.items()
            if band.n < seeds or not len(band.steps) or band.steps[-1] < steps]


# ---------------------------------------------------------------------------------------------

FINAL_DOC = ("Final return: the `return` of the last evaluation (eval.csv's last row, itself "
             "the mean over that evaluation's episodes) of each finished run (done.json), then "
             "mean ± sample std (ddof=1) across seeds. Unfinished runs are not averaged in; "
             "the last column lists them with the step of their last evaluation.")
QUERIES_DOC = ("Final return (as in the final-return table) by number of queries: a row per "
               "budget (each run's `feedback.budget`), a column per variant; mean ± sample std "
               "across finished seeds, `(n=k)` when fewer than the spec's seeds finished.")
DISTINGUISHABILITY_DOC = (
    "Distinguishable ratio of the selected queries (rounds.csv `distinguishable_ratio`): per "
    "run the mean over every round after the first (the first round is uniform for every "
    "method), then mean ± sample std across seeds (unfinished runs count with the rounds they "
    "have; runs with fewer than two rounds are left out). The column header gives each "
    "variant's selection rule (`feedback.selection`).")
CURVES_DOC = (
    "Each line is the mean evaluation return across seeds, the band ± one sample std. Seeds "
    "that evaluated at different steps are interpolated linearly onto the union of their "
    "evaluation steps within the range all of them reached, so a curve stops at its shortest "
    "seed's last evaluation; seeds with no evaluation yet are left out.")
SAME_AGENT_DOC = (
    "Distinguishable ratio of the variant's own selection rule and of the compared rule "
    "(`feedback.compare_rule`) on the same agent, pool and reward model: each round the "
    "compared rule also picks queries, which are only judged by a copy of the teacher "
    "(rounds.csv `compare_distinguishable_ratio`). Per run both are averaged over the same "
    "rounds (after the first, where the compared ratio is logged), then mean ± sample std "
    "across seeds. Only runs that set `feedback.compare_rule`.")
DIAGNOSTICS_DOC = (
    "Per run: the mean of rounds.csv `reward_corr` (Pearson correlation of the learned with "
    "the true reward over the replay buffer after each round) over all rounds and its last "
    "round's value, and the means of `max_trajectory_share` (the largest share of a round's "
    "queries one trajectory took part in) and `trajectory_pairs` (distinct trajectory pairs "
    "among a round's queries) over the rounds after the first; for S-EPOA, whose z_task is "
    "drawn again as each round closes, the means over those rounds of `task_skill_cosine` "
    "(the new z_task's cosine with the one before: 1, unchanged) and `task_skill_gain` "
    "(R_θ of the new z_task less R_θ of the one before, under the refitted R_θ); then mean ± "
    "sample std across seeds (unfinished runs count with the rounds they have).")
PROPOSITION_DOC = (
    "Proposition 1: if each member's segment returns are r̂ ~ N(r, c), the ensemble's Var[P] "
    "of P = sigmoid(r̂₁ − r̂₂) falls as the true gap r₁ − r₂ grows, so the disagreement rule "
    "picks pairs of similar return. Left: Monte Carlo for c = 0.25, 1, 4. Right: the "
    "population variance of P across the members of a trained reward model, for 20 000 random "
    "segment pairs of its run's final pool, averaged per quantile bin of the true segment-"
    "return gap; one finished run per query-selecting variant (its lowest seed, from its "
    "checkpoint.pt). The table gives each run's Spearman rank correlation of gap and Var[P] "
    "over all pairs (negative: the proposition holds).")


PREREGISTERED_DOC = (
    "The spec's `[analysis]`, fixed before its runs: the primary metric of a run is "
    "{metric}. Per variant, the interquartile mean (IQM) and the mean over its finished runs "
    "with 95 % stratified-bootstrap intervals; then the probability that a run of the first "
    "variant scores above a run of the second (ties count half), with its 95 % interval "
    "(rliable). The figure shows the IQM of the evaluation return over the finished runs at "
    "each evaluation, with its 95 % interval.")
MECHANISM_DOC = (
    "Per variant, the mean over its runs (finished or not: what they logged) with a 95 % "
    "bootstrap interval and the runs counted. SAC updates and those on r̂: episodes.csv's last "
    "row (every algorithm makes one SAC update per update step). Pretraining steps: S-EPOA's "
    "skill snapshot, the PEBBLE family's unsupervised phase. Distinguishable ratio: rounds.csv "
    "`distinguishable_ratio` over the rounds after the first; same agent, compared rule: "
    "`compare_distinguishable_ratio`, the compared rule's picks on the same pool and model over "
    "the same rounds; own rule − compared: per run the mean over those rounds of the two "
    "ratios' difference, so its interval is that of a paired comparison. Held-out accuracy: "
    "`model_agreement`, the reward model before a round "
    "scored on that round's new labels, which it has not trained on (rounds after the first).")
EQUAL_UPDATES_DOC = (
    "Secondary, not pre-registered. The finished runs of the compared variants end with "
    "different counts of SAC updates on r̂ (episodes.csv `reward_updates`; S-EPOA learns only "
    "after its initial skill rollouts), the fewest {budget:.0f}. Here each run is scored by its "
    "mean evaluation return over the evaluations taken while its updates on r̂ lay in the last "
    "quarter of that count, [{low:.0f}, {budget:.0f}], so every arm is scored after the same "
    "number of updates on its learned reward; then the same IQM and probability-of-improvement "
    "estimates as the pre-registered comparison. Per run: runs.csv `score_equal_updates`.")
ROUNDS_DOC = ("Per variant and round: the mean across runs of the distinguishable ratio of the "
              "selected queries (and of the compared rule's picks on the same agent).")
RUNS_DOC = ("Every planned run with its state (done, stopped by an operator, failed, partial "
            "or not started), the step it reached, its primary metric (finished runs only) "
            "and its counts; where part of the grid trained on another host "
            "(scripts/grid_part_on_gpu.sh), the GPU each such run trained on.")


def preregistered_sections(results: Results, out: Path
                           ) -> tuple[list[str], dict[str, pd.DataFrame],
                                      dict[str, tuple[str, str, str]]]:
    """For a spec with `[analysis]`: the report's opening lines on it, its tables and its
    sections (see experiments/preregistered.py)."""
    analysis = results.spec.analysis
    assert analysis is not None
    runs = preregistered.per_run(results)
    primary = preregistered.primary_table(results, runs)
    improvement = preregistered.improvement_table(results, runs)
    mechanism = preregistered.mechanism_table(results, runs)
    rounds = preregistered.rounds_table(results)
    bands = preregistered.iqm_bands(results, runs)
    rows = [f"eps {e:g}" for e in results.spec.eps]
    (out / "iqm-curves.png").write_bytes(grid_png(
        {(rows[0], results.spec.tasks[0]): bands}, rows[:1], list(results.spec.tasks[:1]),
        title=results.spec.title + ": IQM, 95 % CI", ylabel="evaluation return"))
    metric = METRICS[analysis.metric]
    lines = ["## Pre-registered comparison", "", preregistered.status_line(runs), "",
             PREREGISTERED_DOC.format(metric=metric), "",
             preregistered.primary_markdown(primary, improvement), "",
             "![IQM curves](iqm-curves.png)", "",
             "Tables: [preregistered.md](preregistered.md), [primary.csv](primary.csv), "
             "[improvement.csv](improvement.csv), [runs.md](runs.md), [runs.csv](runs.csv).",
             ""]
    tables = {"primary": primary, "improvement": improvement, "runs": runs,
              "mechanism": mechanism, "rounds-distinguishability": rounds}
    sections = {}
    budget = preregistered.equal_updates_budget(results, runs)
    if budget is not None:
        runs = preregistered.with_equal_updates_scores(results, runs, budget)
        tables["runs"] = runs
        equal = preregistered.primary_table(results, runs, "score_equal_updates")
        tables["equal-updates"] = equal = equal[equal["iqm"].notna()] if "iqm" in equal else equal
        tables["equal-updates-improvement"] = equal_improvement = (
            preregistered.improvement_table(results, runs, "score_equal_updates"))
        sections["equal-updates"] = (
            "At equal updates on r̂ (not pre-registered)", EQUAL_UPDATES_DOC.format(
                budget=budget, low=(1 - preregistered.FINAL_SHARE) * budget),
            preregistered.primary_markdown(equal, equal_improvement))
    sections |= {
        "mechanism": ("Mechanism", MECHANISM_DOC, preregistered.mechanism_markdown(mechanism)),
        "rounds-distinguishability": ("Distinguishable ratio per round", ROUNDS_DOC,
                                      preregistered.rounds_markdown(rounds)),
        "runs": ("Every run", RUNS_DOC, preregistered.runs_markdown(runs)),
    }
    (out / "preregistered.md").write_text("\n".join(
        [f"# Pre-registered comparison — {results.spec.title}", "", *lines[2:]]) + "\n")
    return lines, tables, sections


def _grid_markdown(results: Results) -> list[str]:
    """The report's opening: the grid, the variants and how many runs are where."""
    spec = results.spec
    budgets = ", ".join(map(str, spec.budgets)) or "each task's own"
    shared = ", ".join(f"`{k} = {v!r}`" for k, v in spec.overrides.items()) or "none"
    counts = results.runs["state"].value_counts()
    states = ", ".join(f"{counts.get(s, 0)} {s}" for s in STATES)
    return [
        f"# {spec.title}", "",
        f"Spec `{spec.name}` ({spec.kind}): preset `{spec.preset}`, {spec.steps} steps; "
        f"tasks {', '.join(spec.tasks)}; eps {', '.join(f'{e:g}' for e in spec.eps)}; "
        f"seeds {', '.join(map(str, spec.seeds))}; budgets {budgets}; shared overrides: "
        f"{shared}.", "",
        *[f"- **{v.label}**: algo `{v.algo}`"
          + "".join(f", `{k} = {val!r}`" for k, val in v.overrides.items())
          for v in spec.variants], "",
        f"Runs: {len(results.runs)} planned: {states}.", "",
    ]


SKILL_QUALITY_DOC = (
    "Each skill snapshot in the results folder's `snapshots/` (S-EPOA's pretraining), as "
    "`sepoa pretrain` measured it: the task return of random skills, one deterministic "
    "episode each, against as many episodes of uniform random actions (the median, the mean "
    "of the best 5 with a 95 % bootstrap interval over the episodes, the maximum). A snapshot "
    "whose skills do no better than random actions gives S-EPOA no skill near the task to "
    "start from.")


def write_report(folder: str | Path, out: str | Path | None = None) -> list[Path]:
    """Write the figures and tables of the results in `folder` (default out:
    `<folder>/report`); returns the files written."""
    results = load_results(folder)
    spec = results.spec
    out = Path(out) if out is not None else results.folder / "report"
    out.mkdir(parents=True, exist_ok=True)
    metaworld = any(t.startswith("metaworld:") for t in spec.tasks)
    seeds = len(spec.seeds)

    final = final_table(results)
    queries = final[["task", "eps", "budget", "variant", "algo", "return_mean", "return_std",
                     "n", "planned"]] if len(final) else final
    dist = distinguishability_table(results)
    tables = {"final": final, "queries": queries, "distinguishability": dist}
    sections = {
        "final": ("Final return", FINAL_DOC, final_markdown(final, metaworld)),
        "queries": ("Final return by number of queries", QUERIES_DOC,
                    queries_markdown(final, _variants(results), seeds)),
        "distinguishability": ("Distinguishability of the selected queries",
                               DISTINGUISHABILITY_DOC, distinguishability_markdown(dist, seeds)),
    }
    # Sections on rounds.csv columns that older results lack: only when they are there.
    same_agent = same_agent_table(results)
    if len(same_agent):
        tables["same-agent-distinguishability"] = same_agent
        sections["same-agent-distinguishability"] = (
            "Distinguishability on the same agent", SAME_AGENT_DOC,
            same_agent_markdown(same_agent, seeds))
    if any(source in results.rounds for source in DIAGNOSTICS.values()):
        diagnostics = diagnostics_table(results)
        tables["round-diagnostics"] = diagnostics
        sections["round-diagnostics"] = ("Round diagnostics", DIAGNOSTICS_DOC,
                                         diagnostics_markdown(diagnostics, seeds))
    quality = quality_table(results.folder.parent / "snapshots")
    if len(quality):
        tables["skill-quality"] = quality
        sections["skill-quality"] = ("Skill quality of the snapshots", SKILL_QUALITY_DOC,
                                     quality_markdown(quality))
    figures_extra = []
    if any(v.algo != "sac" for v in spec.variants):
        tables["proposition1"], body = proposition_section(results, out)
        sections["proposition1"] = ("Proposition 1: disagreement against the return gap",
                                    PROPOSITION_DOC, body)
        figures_extra.append(out / "proposition1.png")
    opening: list[str] = []
    if spec.analysis is not None:
        opening, more_tables, more_sections = preregistered_sections(results, out)
        tables |= more_tables
        sections = more_sections | sections
        figures_extra += [out / "iqm-curves.png", out / "preregistered.md"]
    for name, table in tables.items():
        table.to_csv(out / f"{name}.csv", index=False)
    for name, (heading, doc, body) in sections.items():
        (out / f"{name}.md").write_text(f"# {heading} — {spec.title}\n\n{doc}\n\n{body}\n")
    figures = write_figures(results, out)

    lines = _grid_markdown(results) + opening + ["## Learning curves", "", CURVES_DOC, ""]
    for name, caption, panels in figures:
        lines += [f"![{caption}]({name})", ""]
        notes = _short_curves(panels, seeds, spec.steps)
        if notes:
            lines += ["Curves with fewer seeds than planned or short of the spec's steps:", ""]
            lines += [f"- {n}" for n in notes] + [""]
    for name, (heading, doc, body) in sections.items():
        lines += [f"## {heading}", "", doc, "", body, "",
                  f"Tables: [{name}.md]({name}.md), [{name}.csv]({name}.csv).", ""]
    (out / "report.md").write_text("\n".join(lines).rstrip() + "\n")
    return ([out / f"{n}.{ext}" for n in tables for ext in ("csv", "md")]
            + [out / name for name, _, _ in figures] + figures_extra + [out / "report.md"])

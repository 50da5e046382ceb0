"""The pre-registered comparison of a spec with an `[analysis]` table.

- Primary metric per run (`final_quarter`): the mean evaluation return over the last 25 % of the
  spec's steps (every eval.csv row at step >= 0.75 x steps). Finished runs only (done.json); a
  comparison drawn while runs are missing is marked partial.
- Per variant: the interquartile mean (IQM) of the runs' metric with a 95 % stratified-bootstrap
  interval (rliable; the strata are the tasks), and the plain mean with its interval.
- Probability of improvement of the reference variant over each compared one (and of any
  further pair `[analysis] also` names), P(X > Y) over pairs of runs (ties count half), with
  its 95 % stratified-bootstrap interval (rliable).
- Curves: the IQM over a variant's finished runs at each evaluation step, with its 95 % interval
  (every task, eps and budget pooled, as in the primary metric; one panel says which).
- Mechanism, per run then per variant (mean and 95 % percentile-bootstrap interval over runs):
  SAC updates and those on r_hat (episodes.csv's last row), pretraining steps, labels used, the
  distinguishable ratio of the selected queries (rounds after the first), the same-agent
  comparison (`compare_distinguishable_ratio`) and the paired difference of the two rules over
  the rounds where both were judged, reward_corr after the last round, and the
  reward model's accuracy on held-out labelled pairs: rounds.csv `model_agreement`, the model
  of the round before scored on a round's new labels before it trains on them (rounds after
  the first).

- Secondary, not pre-registered, where the analysis variants' finished runs end with different
  counts of SAC updates on r_hat (S-EPOA learns only after its initial skill rollouts): each
  run's mean evaluation return while its updates on r_hat lay in the last quarter of the
  fewest any of those runs made, so every arm is scored after the same number of updates on
  its learned reward; the same IQM and probability-of-improvement tables on that score.

Interval estimates are resampled with a fixed seed, so a report is reproducible.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd
from rliable import library as rly
from rliable import metrics

from experiments.results import KEYS, Results, read_metrics
from figures.curves import Band

REPS = 20_000
"""bootstrap resamples of a table's interval"""
CURVE_REPS = 2_000
"""bootstrap resamples per point of a curve"""
FINAL_SHARE = 0.25
"""the last share of the steps the primary metric averages over"""


def _bootstrap(scores: dict[str, Any], func: Callable, reps: int
               ) -> dict[str, tuple[float, float, float]]:
    """{name: (point estimate, low, high)}: rliable's estimates with 95 % stratified-bootstrap
    intervals, each name resampled with the same fixed seed, so that its interval depends on
    its own scores only (not on the names before it, or on how many runs they have)."""
    # rliable's bootstraps draw their indices from NumPy's global generator, not from the
    # `random_state` they are given: seed that one for each name, and give it back as it was.
    outside = np.random.get_state()
    out = {}
    try:
        for name, score in scores.items():
            np.random.seed(0)
            with warnings.catch_warnings():  # rliable passes arch a RandomState, deprecated
                warnings.simplefilter("ignore", FutureWarning)
                point, ci = rly.get_interval_estimates({name: score}, func, reps=reps,
                                                       random_state=np.random.RandomState(0))
            out[name] = (float(np.ravel(point[name])[0]), float(np.ravel(ci[name])[0]),
                         float(np.ravel(ci[name])[-1]))
    finally:
        np.random.set_state(outside)
    return out


def _mean_interval(values: np.ndarray, reps: int) -> tuple[float, float]:
    """A 95 % percentile-bootstrap interval of the mean of `values` (seeded)."""
    rng = np.random.default_rng(0)
    means = values[rng.integers(0, len(values), (reps, len(values)))].mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return float(low), float(high)


def _iqm(x: np.ndarray) -> np.ndarray:
    return np.array([metrics.aggregate_iqm(x)])


def _mean(x: np.ndarray) -> np.ndarray:
    return np.array([metrics.aggregate_mean(x)])


def final_quarter(evals: pd.DataFrame, steps: int) -> float:
    """A run's mean evaluation return over its evaluations in the last quarter of `steps`."""
    last = evals[evals["step"] >= (1 - FINAL_SHARE) * steps]
    return float(last["return"].mean()) if len(last) else math.nan


def learned_reward_column(algo: str) -> str:
    """episodes.csv's count of a run's SAC updates on the reward its agent learns from: r_hat
    (`reward_updates`; a run on the true reward, `reward.true_reward`, counts its updates there
    too), or for the SAC oracle, which learns from the true reward alone, all its `updates`."""
    return "updates" if algo == "sac" else "reward_updates"


def _learned_reward_updates(folder: Any, algo: str) -> pd.Series:
    """A run's cumulative SAC updates on its learned reward by step (episodes.csv; a resumed
    run's rewritten rows count once, the last)."""
    frame = read_metrics(folder / "episodes.csv")
    column = learned_reward_column(algo)
    if frame is None or column not in frame:
        return pd.Series(dtype=float)
    return frame.set_index("step")[column].astype(float)


def score_at_updates(evals: pd.DataFrame, updates: pd.Series, budget: float) -> float:
    """A run's mean evaluation return over the evaluations taken while its updates on its
    learned reward (the last episode row at or before the evaluation's step) lay in the last
    quarter of `budget`; NaN if it took none there."""
    if updates.empty:
        return math.nan
    at = updates.reindex(evals["step"].to_numpy(), method="ffill").to_numpy()
    keep = (at >= (1 - FINAL_SHARE) * budget) & (at <= budget)
    return float(evals["return"].to_numpy(float)[keep].mean()) if keep.any() else math.nan


def _last_episode_row(folder: Any) -> dict[str, Any]:
    try:
        frame = pd.read_csv(folder / "episodes.csv")
    except (OSError, pd.errors.EmptyDataError):
        return {}
    return frame.iloc[-1].to_dict() if len(frame) else {}


def _config(folder: Any) -> dict[str, Any]:
    try:
        return json.loads((folder / "config.json").read_text())
    except (OSError, ValueError):
        return {}


TRAINED_ON = "trained_on.txt"
"""where a run trained outside the grid's own workers (scripts/grid_part_on_gpu.sh writes it:
config.json says only `auto`)"""


def _trained_on(folder: Any) -> str:
    """The first field of the run's trained_on.txt (the GPU's name), or "" where it has none."""
    try:
        return (folder / TRAINED_ON).read_text().split(",")[0].strip()
    except OSError:
        return ""


def pretraining_steps(config: dict[str, Any]) -> int:
    """Environment steps a run's agent learned from before its reward existed: S-EPOA's skill
    snapshot, PEBBLE's family's unsupervised phase; 0 for the SAC oracle."""
    algo = config.get("algo")
    if algo == "sepoa":
        return int(config["skill"]["pretrain_steps"])
    if algo == "sac" or not config:
        return 0
    return int(config["unsup_steps"])


def per_run(results: Results) -> pd.DataFrame:
    """One row per planned run: KEYS, algo, state, the primary metric (finished runs only) and
    the mechanism figures (whatever the run has logged)."""
    rows = []
    rounds_by_run = {k: g.sort_values("step", kind="stable")
                     for k, g in results.rounds.groupby(KEYS, sort=False)}
    evals_by_run = dict(iter(results.evals.groupby(KEYS, sort=False)))
    for run in results.runs.itertuples():
        key = tuple(getattr(run, k) for k in KEYS)
        folder = results.folder / run.dir
        evals = evals_by_run.get(key)
        episode = _last_episode_row(folder)
        config = _config(folder)
        row = {k: getattr(run, k) for k in KEYS} | {
            "algo": run.algo, "state": run.state, "step": run.step,
            "score": (final_quarter(evals, run.planned_steps)
                      if run.state == "done" and evals is not None else math.nan),
            "updates": episode.get("updates", math.nan),
            "reward_updates": episode.get("reward_updates", math.nan),
            "learned_reward_updates": episode.get(learned_reward_column(run.algo), math.nan),
            "pretraining_steps": pretraining_steps(config) if config else math.nan,
            "trained_on": _trained_on(folder),
        }
        rounds = rounds_by_run.get(key)
        if rounds is not None and len(rounds):
            later = rounds.iloc[1:]
            # Rounds that ask nothing (`reward.true_reward`) log neither labels nor queries.
            if "labels_used" in rounds:
                row["labels_used"] = rounds["labels_used"].iloc[-1]
            row["rounds"] = len(rounds)
            if len(later) and "distinguishable_ratio" in later:
                row["distinguishable"] = later["distinguishable_ratio"].mean()
                if "model_agreement" in later:
                    row["heldout_accuracy"] = later["model_agreement"].mean()
                if "compare_distinguishable_ratio" in later:
                    row["compared_distinguishable"] = later[
                        "compare_distinguishable_ratio"].mean()
                    both = later[["distinguishable_ratio",
                                  "compare_distinguishable_ratio"]].dropna()
                    if len(both):  # the paired difference, round by round
                        row["same_agent_gain"] = float(
                            (both.iloc[:, 0] - both.iloc[:, 1]).mean())
            if "reward_corr" in rounds:
                row["reward_corr_last"] = rounds["reward_corr"].iloc[-1]
        rows.append(row)
    return pd.DataFrame(rows)


def equal_updates_budget(results: Results, runs: pd.DataFrame) -> float | None:
    """The fewest updates on its learned reward (`learned_reward_column`) a finished run of the
    analysis variants made, where their finished runs' counts differ; None where they are all
    equal (the primary metric already compares them at equal updates) or unknown."""
    analysis = results.spec.analysis
    assert analysis is not None
    compared = runs[runs["variant"].isin([analysis.reference, *analysis.compare_to])
                    & (runs["state"] == "done")]["learned_reward_updates"].dropna()
    if compared.empty or compared.min() == compared.max() or compared.min() <= 0:
        return None
    return float(compared.min())


def with_equal_updates_scores(results: Results, runs: pd.DataFrame, budget: float
                              ) -> pd.DataFrame:
    """`runs` with `score_equal_updates`: each finished run's `score_at_updates` at
    `budget` (NaN for runs that never made that many updates on their learned reward)."""
    evals_by_run = dict(iter(results.evals.groupby(KEYS, sort=False)))
    folders = {tuple(getattr(run, k) for k in KEYS): results.folder / run.dir
               for run in results.runs.itertuples()}
    scores = []
    for run in runs.itertuples():
        key = tuple(getattr(run, k) for k in KEYS)
        evals = evals_by_run.get(key)
        done = (run.state == "done" and evals is not None
                and run.learned_reward_updates >= budget)
        scores.append(score_at_updates(evals, _learned_reward_updates(folders[key], run.algo),
                                       budget) if done else math.nan)
    return runs.assign(score_equal_updates=scores)


def _scores(runs: pd.DataFrame, column: str, variants: list[str]) -> dict[str, np.ndarray]:
    """{variant: (runs, tasks)} of `column` over runs with a value: rliable's layout, the tasks
    its strata. With several tasks a variant's array is as long as its task with the fewest
    such runs (the tables say how many runs they scored, so a cut shows)."""
    out = {}
    tasks = list(dict.fromkeys(runs["task"]))
    for variant in variants:
        sub = runs[(runs["variant"] == variant) & runs[column].notna()]
        columns = [sub[sub["task"] == t][column].to_numpy(float) for t in tasks]
        n = min((len(c) for c in columns), default=0)
        if n:
            out[variant] = np.stack([c[:n] for c in columns], axis=1)
    return out


def primary_table(results: Results, runs: pd.DataFrame, column: str = "score"
                  ) -> pd.DataFrame:
    """Per variant: finished and planned runs, the runs scored (finished with a value of the
    primary metric, or of another per-run score `column`, as `_scores` keeps them), and the
    IQM and mean of those scores with their 95 % intervals."""
    variants = [v.label for v in results.spec.variants]
    scores = _scores(runs, column, variants)
    iqm = _bootstrap(scores, _iqm, REPS) if scores else {}
    mean = _bootstrap(scores, _mean, REPS) if scores else {}
    rows = []
    for variant in variants:
        sub = runs[runs["variant"] == variant]
        row = {"variant": variant, "algo": sub["algo"].iloc[0],
               "finished": int((sub["state"] == "done").sum()), "planned": len(sub),
               "scored": int(scores[variant].size) if variant in scores else 0}
        if variant in scores:
            row |= dict(zip(("iqm", "iqm_low", "iqm_high"), iqm[variant], strict=True))
            row |= dict(zip(("mean", "mean_low", "mean_high"), mean[variant], strict=True))
            if len(scores[variant]) < 2:  # one run resamples to itself: no interval
                row |= dict.fromkeys(("iqm_low", "iqm_high", "mean_low", "mean_high"), math.nan)
        rows.append(row)
    return pd.DataFrame(rows)


def improvement_table(results: Results, runs: pd.DataFrame, column: str = "score"
                      ) -> pd.DataFrame:
    """P(reference > other) of the primary metric (or `column`), with its 95 % interval, per
    compared variant that has finished runs."""
    analysis = results.spec.analysis
    assert analysis is not None
    pairs = analysis.pairs()
    scores = _scores(runs, column, list(dict.fromkeys(x for pair in pairs for x in pair)))
    rows = []
    for reference, other in pairs:
        row = {"reference": reference, "other": other,  # runs, over every task
               "n_reference": scores[reference].size if reference in scores else 0,
               "n_other": scores[other].size if other in scores else 0}
        if reference in scores and other in scores:
            pair = {f"{reference},{other}": (scores[reference], scores[other])}
            (estimate,) = _bootstrap(pair, metrics.probability_of_improvement, REPS).values()
            row |= dict(zip(("probability", "low", "high"), estimate, strict=True))
        rows.append(row)
    return pd.DataFrame(rows)


MECHANISM = {
    "updates": ("SAC updates", 0),
    "reward_updates": ("updates on r̂", 0),
    "pretraining_steps": ("pretraining steps", 0),
    "labels_used": ("labels used", 0),
    "distinguishable": ("distinguishable ratio", 3),
    "compared_distinguishable": ("same agent, compared rule", 3),
    "same_agent_gain": ("own rule − compared, same rounds", 3),
    "reward_corr_last": ("reward corr (last round)", 3),
    "heldout_accuracy": ("held-out accuracy", 3),
}
"""per-run column -> Markdown header and decimals"""


def mechanism_table(results: Results, runs: pd.DataFrame) -> pd.DataFrame:
    """Per variant and mechanism column: the mean over its runs (finished or not: what they
    logged) with a 95 % bootstrap interval, and the runs counted."""
    variants = [v.label for v in results.spec.variants]
    rows = []
    for variant in variants:
        sub = runs[runs["variant"] == variant]
        row: dict[str, Any] = {"variant": variant, "algo": sub["algo"].iloc[0]}
        for column in MECHANISM:
            if column not in sub or not sub[column].notna().any():
                continue
            values = sub[column].dropna().to_numpy(float)
            row[f"{column}_n"] = len(values)
            row[column] = float(values.mean())
            if len(values) > 1:
                row[f"{column}_low"], row[f"{column}_high"] = _mean_interval(values, REPS)
        rows.append(row)
    return pd.DataFrame(rows)


def rounds_table(results: Results) -> pd.DataFrame:
    """Per variant and round: the mean distinguishable ratio of the selected queries (and of
    the compared rule's, where logged) across runs, and the runs counted."""
    if results.rounds.empty or "round" not in results.rounds \
            or "distinguishable_ratio" not in results.rounds:  # rounds that asked nothing
        return pd.DataFrame(columns=["variant", "round", "distinguishable", "n"])
    agg = {"distinguishable": ("distinguishable_ratio", "mean"),
           "n": ("distinguishable_ratio", "count")}
    if "compare_distinguishable_ratio" in results.rounds:
        agg["compared"] = ("compare_distinguishable_ratio", "mean")
    table = results.rounds.groupby(["variant", "round"], sort=False).agg(**agg).reset_index()
    order = {v.label: i for i, v in enumerate(results.spec.variants)}
    return table.sort_values(["variant", "round"], key=lambda c: c.map(order)
                             if c.name == "variant" else c, kind="stable")


def iqm_bands(results: Results, runs: pd.DataFrame) -> dict[str, Band]:
    """Per variant: the IQM of the evaluation return over its finished runs at each evaluation
    step they share, with the 95 % interval as the band. Each run is one value, whatever its
    task, eps or budget: the runs the primary table scores, pooled as it pools them."""
    done = runs[runs["state"] == "done"][KEYS]
    evals = results.evals.merge(done, on=KEYS)
    bands = {}
    for variant in [v.label for v in results.spec.variants]:
        sub = evals[evals["variant"] == variant]
        if sub.empty:
            continue
        table = sub.pivot_table(index="step", columns=[k for k in KEYS if k != "variant"],
                                values="return")
        table = table.dropna()
        if table.empty:
            continue
        steps: list[float] = []
        mid: list[float] = []
        low: list[float] = []
        high: list[float] = []
        for step, row in table.iterrows():
            estimate = _bootstrap({variant: row.to_numpy(float)[:, None]}, _iqm, CURVE_REPS)
            steps.append(step)
            for out, value in zip((mid, low, high), estimate[variant], strict=True):
                out.append(value)
        n = table.shape[1]
        bands[variant] = Band(np.array(steps, float), np.array(mid), np.zeros(len(steps)), n,
                              np.array(low), np.array(high))
    return bands


# ---------------------------------------------------------------------------------------------
# Markdown.

def _interval(value: float, low: float, high: float, digits: int) -> str:
    if not math.isfinite(value):
        return "–"
    if not (math.isfinite(low) and math.isfinite(high)):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def status_line(runs: pd.DataFrame) -> str:
    """Whether the comparison is complete: every planned run finished."""
    done, planned = int((runs["state"] == "done").sum()), len(runs)
    if done == planned:
        return f"**Complete**: all {planned} planned runs finished."
    states = runs["state"].value_counts()
    others = ", ".join(f"{n} {s}" for s, n in states.items() if s != "done")
    return (f"**Partial**: {done} of {planned} planned runs finished ({others}). The figures "
            "below use the finished runs only and will change as the others finish; no "
            "conclusion is drawn from them yet.")


def _finished(r: Any) -> str:
    """A primary table's runs cell: finished of planned, and the runs scored where a finished
    run has no score (no evaluation in the window, or cut to another task's count)."""
    scored = getattr(r, "scored", r.finished)
    return f"{r.finished}/{r.planned}" + (f", {scored} scored" if scored < r.finished else "")


def primary_markdown(primary: pd.DataFrame, improvement: pd.DataFrame) -> str:
    rows = [[r.variant, r.algo, _finished(r),
             _interval(getattr(r, "iqm", math.nan), getattr(r, "iqm_low", math.nan),
                       getattr(r, "iqm_high", math.nan), 1),
             _interval(getattr(r, "mean", math.nan), getattr(r, "mean_low", math.nan),
                       getattr(r, "mean_high", math.nan), 1)]
            for r in primary.itertuples()]
    body = _table(["variant", "algo", "runs finished", "IQM [95 % CI]", "mean [95 % CI]"], rows)
    rows = [[r.reference, r.other, f"{r.n_reference} vs {r.n_other}",
             _interval(getattr(r, "probability", math.nan), getattr(r, "low", math.nan),
                       getattr(r, "high", math.nan), 2)]
            for r in improvement.itertuples()]
    return body + "\n\n" + _table(
        ["variant X", "variant Y", "runs", "P(X > Y) [95 % CI]"], rows)


def mechanism_markdown(mechanism: pd.DataFrame) -> str:
    have = [c for c in MECHANISM if c in mechanism]
    rows = []
    for _, r in mechanism.iterrows():
        cells = [r["variant"], r["algo"]]
        for column in have:
            digits = MECHANISM[column][1]
            n = r.get(f"{column}_n")
            if n is None or not math.isfinite(n):
                cells.append("–")
                continue
            text = _interval(r[column], r.get(f"{column}_low", math.nan),
                             r.get(f"{column}_high", math.nan), digits)
            cells.append(f"{text} (n={int(n)})")
        rows.append(cells)
    return _table(["variant", "algo"] + [MECHANISM[c][0] for c in have], rows)


def rounds_markdown(rounds: pd.DataFrame) -> str:
    if rounds.empty:
        return "No rounds yet."
    variants = list(dict.fromkeys(rounds["variant"]))
    numbers = sorted(set(rounds["round"]))
    rows = []
    for variant in variants:
        sub = rounds[rounds["variant"] == variant].set_index("round")
        rows.append([variant] + [
            f"{sub.loc[k, 'distinguishable']:.2f}" if k in sub.index else "–" for k in numbers])
        if "compared" in sub and sub["compared"].notna().any():
            rows.append([f"{variant}: compared rule"] + [
                f"{sub.loc[k, 'compared']:.2f}"
                if k in sub.index and math.isfinite(sub.loc[k, "compared"]) else "–"
                for k in numbers])
    return _table(["variant"] + [f"round {int(k)}" for k in numbers], rows)


def runs_markdown(runs: pd.DataFrame) -> str:
    def number(value: Any, digits: int) -> str:
        return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"

    rows = [[r.variant, str(r.seed), r.state, number(r.step, 0), number(r.score, 1),
             number(r.updates, 0), number(r.reward_updates, 0),
             number(getattr(r, "labels_used", math.nan), 0)]
            for r in runs.itertuples()]
    header = ["variant", "seed", "state", "step", "primary metric", "SAC updates",
              "updates on r̂", "labels used"]
    # Only a grid trained partly elsewhere (a GPU host) says where each run trained.
    if "trained_on" in runs and runs["trained_on"].fillna("").astype(bool).any():
        header.append("trained on")
        for row, where in zip(rows, runs["trained_on"].fillna(""), strict=True):
            row.append(where or "the grid's workers")
    return _table(header, rows)

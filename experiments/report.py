"""A spec's report: learning-curve figures and Markdown + CSV tables, indexed by report.md.

The numbers of the tables are defined in experiments/tables.py (docs/EXPERIMENTS.md says the
same); besides them:
- Proposition 1: Monte Carlo Var[P] against the return gap, and the measured curve of one
  finished, checkpointed run per query-selecting variant (its lowest seed); see proposition.py.
- Curves: see `plots.align` (common step range of the seeds with at least one evaluation,
  linear interpolation, mean ± one sample std).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from experiments import preregistered
from experiments.agent_table import DOC as AGENT_DOC
from experiments.agent_table import agent_markdown, agent_table
from experiments.progress import duration_text
from experiments.proposition import (
    measured_disagreement,
    proposition_png,
    simulated_disagreement,
)
from experiments.results import KEYS, STATES, Results, load_results
from experiments.sessions import worked
from experiments.skill_quality import quality_markdown, quality_table, snapshots_quality_files
from experiments.spec import METRICS, Spec, grid_snapshots
from experiments.stop_rule import recorded_stop_rule
from experiments.tables import (
    DIAGNOSTICS,
    diagnostics_markdown,
    diagnostics_table,
    distinguishability_markdown,
    distinguishability_table,
    final_markdown,
    final_table,
    markdown_table,
    queries_markdown,
    same_agent_markdown,
    same_agent_table,
    variant_labels,
)
from figures.curves import Band, align, grid_png

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
        body.append(markdown_table(
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
            for variant in variant_labels(results):
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


def _short_curves(panels: dict[tuple[str, str], dict[str, Band]], seeds: Mapping[str, int],
                  steps: int) -> list[str]:
    """Curves with fewer seeds than their variant planned, or that stop before the spec's
    steps."""
    return [f"{col}, {row}: {label}: {band.n} of {seeds[label]} seeds"
            + (f", up to step {band.steps[-1]:g}" if len(band.steps) else ", no evaluation")
            for (row, col), curves in panels.items() for label, band in curves.items()
            if band.n < seeds[label] or not len(band.steps) or band.steps[-1] < steps]


# ---------------------------------------------------------------------------------------------

FINAL_DOC = ("Final return: the `return` of the last evaluation (eval.csv's last row, itself "
             "the mean over that evaluation's episodes) of each finished run (done.json), then "
             "mean ± sample std (ddof=1) across seeds. Unfinished runs are not averaged in; "
             "the last column lists them with the step of their last evaluation, and any "
             "finished run without an evaluation, which the mean's `(n=k)` leaves out.")
QUERIES_DOC = ("Final return (as in the final-return table) by number of queries: a row per "
               "budget (each run's `feedback.budget`), a column per variant; mean ± sample std "
               "across finished seeds, `(n=k)` when fewer than the variant's planned seeds "
               "finished.")
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
    "with 95 % stratified-bootstrap intervals (the runs column says how many were scored "
    "where a finished run has no evaluation to average); then the probability that a run of "
    "the first variant scores above a run of the second (ties count half), with its 95 % "
    "interval (rliable). The figure shows the IQM of the evaluation return over the finished "
    "runs at each evaluation, with its 95 % interval.")
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
    "different counts of SAC updates on the reward their agent learns from (episodes.csv "
    "`reward_updates`: r̂, or the true reward for a run with `reward.true_reward`; the SAC "
    "oracle's `updates`, all on the true reward; S-EPOA learns only after its initial skill "
    "rollouts), the fewest {budget:.0f}. Here each run is scored by its mean evaluation return "
    "over the evaluations taken while those updates lay in the last quarter of that count, "
    "[{low:.0f}, {budget:.0f}], so every arm is scored after the same number of updates on "
    "its reward; then the same IQM and probability-of-improvement estimates as the "
    "pre-registered comparison. Per run: runs.csv `score_equal_updates`.")
ROUNDS_DOC = ("Per variant and round: the mean across runs of the distinguishable ratio of the "
              "selected queries (and of the compared rule's picks on the same agent).")
RUNS_DOC = ("Every planned run with its state (done, stopped by an operator, failed, partial "
            "or not started), the step it reached, its primary metric (finished runs only) "
            "and its counts; where part of the grid trained on another host "
            "(scripts/grid_part_on_gpu.sh), the GPU each such run trained on.")


def _pooled(spec: Spec) -> tuple[str, str]:
    """The IQM curves' one panel, named by what its runs pool: (eps and budgets, tasks)."""
    def named(things: list[str]) -> str:
        return ", ".join(things) + (" pooled" if len(things) > 1 else "")
    row = "eps " + named([f"{e:g}" for e in spec.eps])
    if len(spec.budgets) > 1:
        row += "; budgets " + named([str(b) for b in spec.budgets])
    return row, named(list(spec.tasks))


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
    row, col = _pooled(results.spec)
    (out / "iqm-curves.png").write_bytes(grid_png(
        {(row, col): bands}, [row], [col], title=results.spec.title + ": IQM, 95 % CI",
        ylabel="evaluation return"))
    metric = METRICS[analysis.metric]
    period = worked(results.folder)  # what a stop rule in wall time reads
    rule = recorded_stop_rule(results.spec, results.folder)
    lines = ["## Pre-registered comparison", "", preregistered.status_line(runs), "",
             *([period.text(duration_text(period.seconds)) + ".", ""] if period else []),
             *([rule.text(duration_text) + ".", ""] if rule else []),
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
            "At equal updates on the learned reward (not pre-registered)", EQUAL_UPDATES_DOC.format(
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
    "Each skill snapshot the grid's runs start from (S-EPOA's pretraining), as "
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
    seeds = {v.label: len(v.seeds or spec.seeds) for v in spec.variants}  # each one's own

    final = final_table(results)
    queries = final[["task", "eps", "budget", "variant", "algo", "return_mean", "return_std",
                     "n", "planned"]] if len(final) else final
    dist = distinguishability_table(results)
    tables = {"final": final, "queries": queries, "distinguishability": dist}
    sections = {
        "final": ("Final return", FINAL_DOC, final_markdown(final, metaworld)),
        "queries": ("Final return by number of queries", QUERIES_DOC,
                    queries_markdown(final, variant_labels(results), seeds)),
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
    agent = agent_table(results)
    tables["agent"] = agent
    sections["agent"] = ("How the agents trained", AGENT_DOC, agent_markdown(agent, seeds))
    # The grid's own snapshots: kept beside its runs (`experiment keep`), else in the results
    # folder's shared snapshots/.
    quality = quality_table(snapshots_quality_files(
        grid_snapshots(results.spec), [results.folder / "snapshots",
                                       results.folder.parent / "snapshots"]))
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

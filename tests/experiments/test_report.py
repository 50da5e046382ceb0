"""The report's numbers on hand-written results: final returns, the query-count and
distinguishability tables (sample std), curve alignment on unequal step grids, partial seeds,
and PNG figures."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from experiments.report import curve_panels, write_report
from experiments.results import load_results
from experiments.spec import SpecError
from experiments.tables import mean_std
from figures.curves import PNG_SIGNATURE, Band, align, curves_png, grid_figure

ROOT = Path(__file__).resolve().parents[2]

SPEC = """
name = "synthetic"
title = "Synthetic results"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]
budgets = [100, 200]

[variants.A]
algo = "pebble"

[variants.B]
algo = "sepoa"
"""

# (variant, budget, seed) -> eval rows (step, return); the last row is the final return.
EVALS = {
    ("A", 100, 0): [(200, 1.0), (400, 2.0), (600, 10.0)],
    ("A", 100, 1): [(250, 2.0), (450, 4.0), (600, 20.0)],
    ("B", 100, 0): [(200, 5.0), (400, 6.0), (600, 30.0)],
    ("B", 100, 1): [(200, 5.0), (400, 6.0), (600, 34.0)],
    ("A", 200, 0): [(200, 1.0), (400, 2.0), (600, 40.0)],
    ("A", 200, 1): [(200, 1.0), (400, 2.0), (600, 44.0)],
    ("B", 200, 0): [(200, 5.0), (400, 6.0), (600, 50.0)],
    ("B", 200, 1): [(200, 7.0), (400, 9.0)],  # partial: stopped after step 400
}
# distinguishable_ratio per round; the first round is left out of the table.
ROUNDS = {
    ("A", 100, 0): [0.0, 0.4, 0.6],
    ("A", 100, 1): [1.0, 0.2, 0.4, 0.3],
    ("B", 100, 0): [0.5, 0.8],
    ("B", 100, 1): [0.5, 0.9],
}
SELECTION = {"A": "disagreement", "B": "skill"}


def _write_csv(path: Path, header: str, rows: list[str]) -> None:
    path.write_text("\n".join([header, *rows]) + "\n")


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic results folder, its report written by `sepoa report` into report/."""
    folder = tmp_path_factory.mktemp("results") / "synthetic"
    folder.mkdir()
    (folder / "spec.toml").write_text(SPEC)
    for (variant, budget, seed), evals in EVALS.items():
        run = folder / "dmc-cheetah_run" / variant / "eps0.3" / f"budget{budget}" / f"s{seed}"
        run.mkdir(parents=True)
        (run / "config.json").write_text(json.dumps(
            {"feedback": {"budget": budget, "selection": SELECTION[variant]}}))
        _write_csv(run / "eval.csv", "step,return,return_std,success_rate,labels_used",
                   [f"{s},{r},0.0,0.0,0" for s, r in evals])
        _write_csv(run / "episodes.csv", "step,episode,return",
                   [f"{s},{i},{r}" for i, (s, r) in enumerate(evals)])
        ratios = ROUNDS.get((variant, budget, seed), [])
        if ratios:
            _write_csv(run / "rounds.csv", "step,round,distinguishable_ratio",
                       [f"{200 * (i + 1)},{i},{r}" for i, r in enumerate(ratios)])
        if evals[-1][0] == 600:
            (run / "done.json").write_text(json.dumps({"step": 600}))
    from sepoa.cli import main

    assert main(["report", str(folder)]) == 0
    return folder


def test_mean_std_is_the_sample_std() -> None:
    mean, std, n = mean_std([10.0, 20.0])
    assert (mean, n) == (15.0, 2)
    assert std == pytest.approx(math.sqrt(50.0))  # ddof=1; the population std would be 5
    assert math.isnan(mean_std([3.0])[1]) and mean_std([])[2] == 0


def test_align_interpolates_onto_the_range_every_seed_covers() -> None:
    band = align([([200, 400, 600], [1.0, 2.0, 3.0]), ([250, 450, 600], [2.0, 4.0, 6.0])])
    assert band.steps.tolist() == [250, 400, 450, 600]
    seed0 = np.array([1.25, 2.0, 2.25, 3.0])
    seed1 = np.array([2.0, 3.5, 4.0, 6.0])
    np.testing.assert_allclose(band.mean, (seed0 + seed1) / 2)
    np.testing.assert_allclose(band.std, np.std([seed0, seed1], axis=0, ddof=1))
    assert band.n == 2
    # A seed that stopped early ends the curve at its last evaluation.
    short = align([([200, 400, 600], [1.0, 2.0, 3.0]), ([200, 400], [3.0, 4.0])])
    assert short.steps.tolist() == [200, 400] and short.n == 2
    # One seed: its own values, no band; no seed: an empty curve.
    one = align([([0, 10], [1.0, 2.0])])
    assert one.mean.tolist() == [1.0, 2.0] and one.std.tolist() == [0.0, 0.0]
    assert align([([], [])]).n == 0


def test_tables_hold_the_expected_numbers(results: Path) -> None:
    out = results / "report"

    final = pd.read_csv(out / "final.csv")
    a100 = final[(final.variant == "A") & (final.budget == 100)].iloc[0]
    assert a100.return_mean == 15.0 and a100.return_std == pytest.approx(math.sqrt(50.0))
    assert (a100.n, a100.planned) == (2, 2)
    # The partial seed is counted but not averaged in.
    b200 = final[(final.variant == "B") & (final.budget == 200)].iloc[0]
    assert (b200.return_mean, b200.n, b200.planned) == (50.0, 1, 2)
    assert math.isnan(b200.return_std)
    assert b200.unfinished == "s1 partial @ 400"

    final_md = (out / "final.md").read_text()
    assert "| A | pebble | 15.0 ± 7.1 | 2/2 | – |" in final_md
    assert "| B | sepoa | 50.0 | 1/2 | s1 partial @ 400 |" in final_md

    queries = (out / "queries.md").read_text()
    assert "| queries | A | B |" in queries
    assert "| 100 | 15.0 ± 7.1 | 32.0 ± 2.8 |" in queries
    assert "| 200 | 42.0 ± 2.8 | 50.0 (n=1) |" in queries

    dist = pd.read_csv(out / "distinguishability.csv")
    a = dist[(dist.variant == "A") & (dist.budget == 100)].iloc[0]
    # Per run the mean after the first round: 0.5 and 0.3; then mean and sample std.
    assert a["mean"] == pytest.approx(0.4) and a["std"] == pytest.approx(math.sqrt(0.02))
    assert (a.selection, a.n) == ("disagreement", 2)
    b = dist[(dist.variant == "B") & (dist.budget == 100)].iloc[0]
    assert b["mean"] == pytest.approx(0.85) and b.selection == "skill"
    dist_md = (out / "distinguishability.md").read_text()
    assert "| task | eps | budget | A (disagreement) | B (skill) |" in dist_md
    assert "| dmc:cheetah_run | 0.3 | 100 | 0.400 ± 0.141 | 0.850 ± 0.071 |" in dist_md
    assert "| dmc:cheetah_run | 0.3 | 200 | – | – |" in dist_md


def test_figures_and_index(results: Path) -> None:
    out = results / "report"
    names = {p.name for p in out.iterdir()}
    # Two budgets: a curve figure each.
    assert {"curves_budget100.png", "curves_budget200.png", "report.md", "final.md",
            "queries.md", "distinguishability.md"} <= names
    for name in ("curves_budget100.png", "curves_budget200.png"):
        assert (out / name).read_bytes().startswith(PNG_SIGNATURE)
    index = (out / "report.md").read_text()
    assert "![evaluation return, 100 queries](curves_budget100.png)" in index
    assert "Runs: 8 planned: 7 done, 0 stopped, 1 partial, 0 failed, 0 not started." in index
    assert "- dmc:cheetah_run, eps 0.3: B: 2 of 2 seeds, up to step 400" in index
    res = load_results(results)
    assert len(res.runs) == 8 and set(res.evals["budget"]) == {100, 200}
    # The partial seed is in its curve, which stops at that seed's last evaluation.
    band = curve_panels(res, "return", ["dmc:cheetah_run"], 200)[("eps 0.3", "dmc:cheetah_run")]
    assert band["B"].steps.tolist() == [200, 400] and band["B"].n == 2
    assert band["A"].steps.tolist() == [200, 400, 600]


@pytest.mark.parametrize("cols", [["cheetah_run"], ["cheetah_run", "walker_run", "hopper"]])
def test_a_figures_title_and_legend_fit_its_width(cols: list[str]) -> None:
    """Long curve labels and a long title, as a spec's variants and title are, on one panel
    and on three: the legend takes fewer columns and the title more lines, nothing is cut."""
    labels = ["S-EPOA", "PEBBLE", "SURF", "S-EPOA, disagreement", "S-EPOA, z_task each episode",
              "SAC oracle on the true reward"]
    panel = {label: [([0, 5000, 10000], [0.0, i, 2.0 * i])] for i, label in enumerate(labels)}
    title = ("S-EPOA against SURF and PEBBLE at equal updates and labels, cheetah_run, eps 0.3 "
             "(small): IQM, 95 % CI")
    fig = grid_figure({("eps 0.3", col): panel for col in cols}, ["eps 0.3"], cols, title=title)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legend = fig.legends[0]
    assert [t.get_text() for t in legend.get_texts()] == labels
    for artist in (fig._suptitle, legend):
        box = artist.get_window_extent(renderer)
        assert box.x0 >= 0 and box.x1 <= fig.bbox.width, artist
        assert box.y0 >= 0 and box.y1 <= fig.bbox.height, artist
    lines = fig._suptitle.get_text().splitlines()
    assert " ".join(lines) == title and len(lines) == (2 if len(cols) == 1 else 1)


def test_report_of_a_folder_without_spec_is_an_error(tmp_path: Path, capsys) -> None:
    from sepoa.cli import main

    assert main(["report", str(tmp_path)]) == 2
    assert "spec.toml: cannot read the spec" in capsys.readouterr().err
    with pytest.raises(SpecError):
        write_report(tmp_path)


def test_a_report_out_that_is_a_file_is_one_line_of_error(results: Path, tmp_path: Path,
                                                           capsys) -> None:
    from sepoa.cli import main

    taken = tmp_path / "afile"
    taken.write_text("mine")
    capsys.readouterr()
    assert main(["report", str(results), "--out", str(taken)]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--out {taken} is a file" in err and len(err.splitlines()) == 1, err
    assert taken.read_text() == "mine"
    # A folder that cannot be made (its parent is a file) says so too.
    assert main(["report", str(results), "--out", str(taken / "report")]) == 2
    err = capsys.readouterr().err.strip()
    assert str(taken) in err and len(err.splitlines()) == 1, err


def test_plots_draw_plain_data_without_torch() -> None:
    png = curves_png({"a": [([0, 1, 2], [0.0, 1.0, 2.0]), ([0, 2], [1.0, 3.0])],
                      "b": Band(np.array([0, 2]), np.array([1.0, 1.0]),
                                np.array([0.1, 0.1]), 3)}, title="t")
    assert png.startswith(PNG_SIGNATURE)
    probe = ("import sys, figures.curves; "
             "print('torch' in sys.modules, 'matplotlib.pyplot' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"]


def test_older_results_get_no_round_sections_and_a_monte_carlo_only_proposition(
        results: Path) -> None:
    out = results / "report"
    names = {p.name for p in out.iterdir()}
    assert not names & {"same-agent-distinguishability.csv", "round-diagnostics.csv"}
    index = (out / "report.md").read_text()
    assert "## Round diagnostics" not in index
    assert "## Distinguishability on the same agent" not in index
    # No run has a checkpoint.pt: the figure shows the Monte Carlo alone.
    assert (out / "proposition1.png").read_bytes().startswith(PNG_SIGNATURE)
    assert "No finished query-selecting run with a checkpoint.pt: Monte Carlo only." in index
    assert pd.read_csv(out / "proposition1.csv").empty


NEW_SPEC = """
name = "diagnosed"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]
budgets = [100]

[variants.A]
algo = "pebble"

[variants.B]
algo = "sepoa"

[variants.S]
algo = "sac"
"""
NEW_HEADER = ("step,round,distinguishable_ratio,reward_corr,trajectory_pairs,"
              "max_trajectory_share,compare_distinguishable_ratio,task_skill_cosine,"
              "task_skill_gain")
# (variant, seed) -> rounds (distinguishable, reward_corr, pairs, max share, compared ratio,
# z_task cosine, z_task gain); A sets no compare_rule (empty column); B compares with
# disagreement from its second round, and draws z_task as S-EPOA does (none before round 1).
NEW_ROUNDS = {
    ("A", 0): [(1.0, 0.0, 10, 0.2, "", "", ""), (0.5, 0.2, 4, 0.6, "", "", "")],
    ("A", 1): [(1.0, 0.1, 10, 0.2, "", "", ""), (0.5, 0.3, 6, 0.4, "", "", "")],
    ("B", 0): [(0.5, 0.1, 10, 0.2, "", "", ""), (0.8, 0.5, 8, 0.3, 0.4, 0.5, 1.0),
               (0.6, 0.7, 6, 0.5, 0.2, 1.0, 0.0)],
    # the last round logged no compared ratio: it is left out of both of its means
    ("B", 1): [(0.5, 0.2, 10, 0.2, "", "", ""), (0.9, 0.6, 9, 0.2, 0.5, 0.9, 2.0),
               (1.0, 0.9, 7, 0.4, "", 0.7, -1.0)],
}
NEW_FEEDBACK = {"A": {"selection": "disagreement"},
                "B": {"selection": "skill", "compare_rule": "disagreement"},
                "S": {"selection": "uniform"}}


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Results whose rounds.csv have the round diagnostics and the compared rule's ratio; their
    report in report/."""
    folder = tmp_path_factory.mktemp("results") / "diagnosed"
    folder.mkdir()
    (folder / "spec.toml").write_text(NEW_SPEC)
    for variant in ("A", "B", "S"):
        for seed in (0, 1):
            run = folder / "dmc-cheetah_run" / variant / "eps0.3" / "budget100" / f"s{seed}"
            run.mkdir(parents=True)
            (run / "config.json").write_text(json.dumps(
                {"feedback": {"budget": 100} | NEW_FEEDBACK[variant]}))
            _write_csv(run / "eval.csv", "step,return", ["600,1.0"])
            rounds = NEW_ROUNDS.get((variant, seed), [])
            if rounds:
                _write_csv(run / "rounds.csv", NEW_HEADER,
                           [",".join(map(str, (200 * (i + 1), i, *r)))
                            for i, r in enumerate(rounds)])
            (run / "done.json").write_text(json.dumps({"step": 600}))
    write_report(folder)
    return folder


def test_same_agent_distinguishability(diagnosed: Path) -> None:
    out = diagnosed / "report"
    table = pd.read_csv(out / "same-agent-distinguishability.csv")
    # Only B compares; A (no compare_rule) and S (sac) have no row.
    assert table["variant"].tolist() == ["B"]
    b = table.iloc[0]
    assert (b.selection, b.compare_rule, b.n) == ("skill", "disagreement", 2)
    # Per run, the rounds after the first with a compared ratio: s0 (0.8, 0.6) vs (0.4, 0.2),
    # s1 0.9 vs 0.5; then mean and sample std across seeds.
    assert b.own_mean == pytest.approx(0.8) and b.own_std == pytest.approx(math.sqrt(0.02))
    assert b.compared_mean == pytest.approx(0.4)
    assert b.compared_std == pytest.approx(math.sqrt(0.02))
    md = (out / "same-agent-distinguishability.md").read_text()
    assert ("| dmc:cheetah_run | 0.3 | 100 | B | skill | 0.800 ± 0.141 | disagreement "
            "| 0.400 ± 0.141 |") in md
    assert "## Distinguishability on the same agent" in (out / "report.md").read_text()


def test_round_diagnostics(diagnosed: Path) -> None:
    out = diagnosed / "report"
    table = pd.read_csv(out / "round-diagnostics.csv").set_index("variant")
    assert table.index.tolist() == ["A", "B"]  # sac selects no queries
    a, b = table.loc["A"], table.loc["B"]
    # reward_corr: mean over all rounds per run (A 0.1, 0.2; B 0.433, 0.567), last round
    assert a.reward_corr_mean_mean == pytest.approx(0.15)
    assert a.reward_corr_mean_std == pytest.approx(math.sqrt(0.005))
    assert b.reward_corr_mean_mean == pytest.approx(0.5)
    assert (a.reward_corr_last_mean, b.reward_corr_last_mean) == pytest.approx((0.25, 0.8))
    # spread: rounds after the first (A 0.6 and 0.4; B 0.4 and 0.3)
    assert (a.max_trajectory_share_mean, b.max_trajectory_share_mean) == pytest.approx(
        (0.5, 0.35))
    assert (a.trajectory_pairs_mean, b.trajectory_pairs_mean) == pytest.approx((5.0, 7.5))
    assert a.trajectory_pairs_std == pytest.approx(math.sqrt(2.0)) and a.n == 2
    # z_task, rounds after the first: B s0 cosine (0.5, 1.0), gain (1, 0); s1 (0.9, 0.7), (2, -1)
    assert b.task_skill_cosine_mean == pytest.approx(0.775)
    assert b.task_skill_cosine_std == pytest.approx(math.sqrt(0.00125))
    assert (b.task_skill_gain_mean, b.task_skill_gain_std) == pytest.approx((0.5, 0.0))
    assert math.isnan(a.task_skill_cosine_mean)  # not S-EPOA: no z_task
    md = (out / "round-diagnostics.md").read_text()
    assert ("| task | eps | budget | variant | reward corr (mean over rounds) "
            "| reward corr (last round) | max trajectory share | trajectory pairs "
            "| z_task cosine to the round before | R_θ gain of the new z_task |") in md
    assert "| dmc:cheetah_run | 0.3 | 100 | A | 0.150 ± 0.071 | 0.250 ± 0.071 | 0.500 ± 0.141 " \
           "| 5.0 ± 1.4 | – | – |" in md
    assert "| dmc:cheetah_run | 0.3 | 100 | B | 0.500 ± 0.094 | 0.800 ± 0.141 | 0.350 ± 0.071 " \
           "| 7.5 ± 0.7 | 0.775 ± 0.035 | 0.50 ± 0.00 |" in md
    index = (out / "report.md").read_text()
    assert "## Round diagnostics" in index
    assert "[round-diagnostics.csv](round-diagnostics.csv)" in index


ANALYSED = """
name = "analysed"
preset = "tiny"
steps = 800
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1, 2, 3]

[analysis]
metric = "final_quarter"
reference = "R"
compare_to = ["X"]

[variants.R]
algo = "sepoa"

[variants.X]
algo = "surf"

[variants.O]
algo = "sac"
seeds = [0, 1]
"""
# Evaluations at 200, 400, 600, 800: the primary metric averages those at >= 600.
LAST_TWO = {("R", 0): (10, 12), ("R", 1): (20, 22), ("R", 2): (30, 32), ("R", 3): (100, 102),
            ("X", 0): (5, 7), ("X", 1): (15, 17), ("X", 2): (25, 27), ("X", 3): (0, 0),
            ("O", 0): (50, 50)}


@pytest.fixture(scope="module")
def analysed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """R and X at 4 seeds (X s3 stopped by an operator at step 400), O at 2 (s1 not
    started), with episodes.csv update counts and rounds.csv held-out accuracy."""
    from experiments import preregistered

    # Fewer resamples than a real report's: the same estimates, intervals a little coarser.
    patch = pytest.MonkeyPatch()
    patch.setattr(preregistered, "REPS", 300)
    patch.setattr(preregistered, "CURVE_REPS", 50)
    folder = tmp_path_factory.mktemp("results") / "analysed"
    folder.mkdir()
    (folder / "spec.toml").write_text(ANALYSED)
    algos = {"R": "sepoa", "X": "surf", "O": "sac"}
    for (variant, seed), (a, b) in LAST_TWO.items():
        run = folder / "dmc-cheetah_run" / variant / "eps0.3" / f"s{seed}"
        run.mkdir(parents=True)
        config = {"algo": algos[variant], "unsup_steps": 200, "skill": {"pretrain_steps": 5000},
                  "feedback": {"budget": 30, "selection": "skill" if variant == "R"
                               else "disagreement"}}
        (run / "config.json").write_text(json.dumps(config))
        stopped = (variant, seed) == ("X", 3)
        evals = [(200, 0), (400, 1)] + ([] if stopped else [(600, a), (800, b)])
        _write_csv(run / "eval.csv", "step,return", [f"{s},{r}" for s, r in evals])
        updates = 400 if stopped else 800
        _write_csv(run / "episodes.csv", "step,episode,return,updates,reward_updates",
                   [f"{updates},1,0,{updates},{updates - 200}"])
        if variant != "O":
            # R also logs the compared rule's picks: 0.5 then 0.6 (0.7 at seed 3).
            compared = (["", "0.5", f"{0.6 + 0.1 * (seed == 3):.1f}"] if variant == "R"
                        else ["", "", ""])
            _write_csv(run / "rounds.csv",
                       "step,round,labels_used,distinguishable_ratio,model_agreement,"
                       "reward_corr,compare_distinguishable_ratio",
                       [f"200,0,10,0.5,,0.1,{compared[0]}",
                        f"400,1,20,{0.6 + 0.1 * (variant == 'R')},0.7,0.2,{compared[1]}",
                        f"600,2,30,0.8,0.9,0.3,{compared[2]}"][:2 if stopped else 3])
        marker = "stopped.json" if stopped else "done.json"
        (run / marker).write_text(json.dumps({"step": 400 if stopped else 800}))
    write_report(folder)
    patch.undo()
    return folder


def test_the_preregistered_comparison_uses_finished_runs_and_rliable_intervals(
        analysed: Path) -> None:
    out = analysed / "report"
    runs = pd.read_csv(out / "runs.csv").set_index(["variant", "seed"])
    # The primary metric: the mean of the evaluations in the last quarter (steps 600 and 800).
    assert runs.loc[("R", 0), "score"] == 11.0 and runs.loc[("R", 3), "score"] == 101.0
    # A stopped run is shown as stopped, with no score; a run never started as not started.
    assert runs.loc[("X", 3), "state"] == "stopped" and math.isnan(runs.loc[("X", 3), "score"])
    assert runs.loc[("O", 1), "state"] == "not started"

    primary = pd.read_csv(out / "primary.csv").set_index("variant")
    r = primary.loc["R"]
    # IQM of 11, 21, 31, 101: the mean of the middle half, 21 and 31.
    assert (r.finished, r.planned) == (4, 4) and r.iqm == pytest.approx(26.0)
    assert r["mean"] == pytest.approx(41.0) and r.iqm_low <= r.iqm <= r.iqm_high
    assert (primary.loc["X", "finished"], primary.loc["X", "planned"]) == (3, 4)
    assert (primary.loc["O", "finished"], primary.loc["O", "planned"]) == (1, 2)
    assert primary.loc["O", "iqm"] == 50.0 and math.isnan(primary.loc["O", "iqm_low"])

    improvement = pd.read_csv(out / "improvement.csv").iloc[0]
    # R: 11, 21, 31, 101 against X: 6, 16, 26. R is higher in 9 of the 12 pairs.
    assert (improvement.reference, improvement.other) == ("R", "X")
    assert improvement.probability == pytest.approx(9 / 12)
    assert improvement.low <= improvement.probability <= improvement.high <= 1.0

    mechanism = pd.read_csv(out / "mechanism.csv").set_index("variant")
    assert mechanism.loc["R", "updates"] == 800 and mechanism.loc["R", "reward_updates"] == 600
    assert mechanism.loc["X", "updates"] == pytest.approx((3 * 800 + 400) / 4)
    assert mechanism.loc["R", "pretraining_steps"] == 5000
    assert mechanism.loc["X", "pretraining_steps"] == 200
    assert mechanism.loc["O", "pretraining_steps"] == 0
    # Rounds after the first: R (0.7 + 0.8) / 2; held-out accuracy (0.7 + 0.9) / 2.
    assert mechanism.loc["R", "distinguishable"] == pytest.approx(0.75)
    assert mechanism.loc["R", "heldout_accuracy"] == pytest.approx(0.8)
    # The same-agent gain is paired round by round: 0.2 at seeds 0-2, (0.2 + 0.1) / 2 at seed 3.
    r = mechanism.loc["R"]
    assert r.compared_distinguishable == pytest.approx((3 * 0.55 + 0.6) / 4)
    assert r.same_agent_gain == pytest.approx((3 * 0.2 + 0.15) / 4)
    assert 0.15 <= r.same_agent_gain_low <= r.same_agent_gain <= r.same_agent_gain_high <= 0.2
    assert math.isnan(mechanism.loc["X", "same_agent_gain"])

    index = (out / "report.md").read_text()
    assert "## Pre-registered comparison" in index
    assert "**Partial**: 8 of 10 planned runs finished" in index
    assert "| R | X | 4 vs 3 | 0.75 [" in index
    assert (out / "iqm-curves.png").read_bytes().startswith(PNG_SIGNATURE)
    assert "| R | 0 | done | 800 | 11.0 | 800 | 600 | 30 |" in (out / "runs.md").read_text()


def test_runs_trained_on_another_host_say_where_in_the_runs_table(analysed: Path,
                                                                   tmp_path: Path) -> None:
    """Part of a grid trained on a GPU host (scripts/grid_part_on_gpu.sh) says so per run, as
    its config.json cannot (its device is `auto`)."""
    import shutil

    from experiments import preregistered

    assert "| trained on |" not in (analysed / "report" / "runs.md").read_text()
    copy = tmp_path / "analysed"
    shutil.copytree(analysed, copy, ignore=shutil.ignore_patterns("report"))
    (copy / "dmc-cheetah_run" / "R" / "eps0.3" / "s1" / "trained_on.txt").write_text(
        "NVIDIA H100 80GB HBM3, 2026-11-26 (scripts/grid_part_on_gpu.sh)\n")
    table = preregistered.runs_markdown(preregistered.per_run(load_results(copy)))
    lines = table.splitlines()
    assert lines[0].endswith("| labels used | trained on |")
    assert "| R | 0 | done | 800 | 11.0 | 800 | 600 | 30 | the grid's workers |" in lines
    assert any(line.startswith("| R | 1 | done |") and line.endswith("| NVIDIA H100 80GB HBM3 |")
               for line in lines)


def test_arms_with_unequal_updates_on_r_hat_are_also_scored_at_equal_updates(
        analysed: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """R learns on r_hat from step 200, X from step 0: the secondary table scores both over
    the last quarter of R's 600 updates on r_hat, R at step 800 and X at step 600."""
    import shutil

    from experiments import preregistered

    # Equal counts (the fixture): no secondary table, the primary metric already is at equal
    # updates.
    assert not (analysed / "report" / "equal-updates.md").exists()
    copy = tmp_path / "analysed"
    shutil.copytree(analysed, copy, ignore=shutil.ignore_patterns("report"))
    for seed in range(4):
        run = copy / "dmc-cheetah_run" / "R" / "eps0.3" / f"s{seed}"
        _write_csv(run / "episodes.csv", "step,episode,return,updates,reward_updates",
                   [f"{s},{s // 200},0,{s},{max(s - 200, 0)}" for s in (200, 400, 600, 800)])
        run = copy / "dmc-cheetah_run" / "X" / "eps0.3" / f"s{seed}"
        if seed < 3:  # X s3 stopped at 400; a resumed run rewrote its row at 600: the last counts
            _write_csv(run / "episodes.csv", "step,episode,return,updates,reward_updates",
                       ["200,1,0,200,200", "400,2,0,400,400", "600,3,0,600,999",
                        "600,3,0,600,600", "800,4,0,800,800"])
    # The SAC oracle learns on the true reward: none of its updates is on r_hat, every one is
    # on the reward it learns from.
    _write_csv(copy / "dmc-cheetah_run" / "O" / "eps0.3" / "s0" / "episodes.csv",
               "step,episode,return,updates,reward_updates",
               [f"{s},{s // 200},0,{s},0" for s in (200, 400, 600, 800)])
    results = load_results(copy)
    runs = preregistered.per_run(results)
    assert preregistered.equal_updates_budget(results, runs) == 600
    runs = preregistered.with_equal_updates_scores(results, runs, 600).set_index(
        ["variant", "seed"])
    for seed in range(3):
        a, b = LAST_TWO[("R", seed)]
        assert runs.loc[("R", seed), "score_equal_updates"] == b  # step 800 only
        assert runs.loc[("X", seed), "score_equal_updates"] == LAST_TWO[("X", seed)][0]  # 600
    # The oracle is scored by its updates on the true reward: 600 at step 600.
    assert runs.loc[("O", 0), "learned_reward_updates"] == 800
    assert runs.loc[("O", 0), "score_equal_updates"] == LAST_TWO[("O", 0)][0]
    # An unfinished run gets no score.
    assert math.isnan(runs.loc[("X", 3), "score_equal_updates"])

    monkeypatch.setattr(preregistered, "REPS", 300)  # as the fixture's: coarser intervals
    monkeypatch.setattr(preregistered, "CURVE_REPS", 50)
    write_report(copy)
    out = copy / "report"
    table = pd.read_csv(out / "equal-updates.csv").set_index("variant")
    assert list(table.index) == ["R", "X", "O"]  # O by its updates on the true reward
    assert table.loc["O", "iqm"] == pytest.approx(50.0)
    # IQM of 12, 22, 32, 102: the middle half, 22 and 32.
    assert table.loc["R", "iqm"] == pytest.approx(27.0)
    improvement = pd.read_csv(out / "equal-updates-improvement.csv").iloc[0]
    # R: 12, 22, 32, 102 against X: 5, 15, 25: R is higher in 1 + 2 + 3 + 3 of the 12 pairs.
    assert improvement.probability == pytest.approx(9 / 12)
    index = (out / "report.md").read_text()
    assert "## At equal updates on the learned reward (not pre-registered)" in index
    assert "the fewest 600" in index and "[450, 600]" in index


TWO_EPS = """
name = "two-eps"
preset = "tiny"
steps = 800
tasks = ["dmc:cheetah_run"]
eps = [0.1, 0.3]
seeds = [0, 1, 2, 3]

[analysis]
metric = "final_quarter"
reference = "R"
compare_to = ["X"]

[variants.R]
algo = "pebble"

[variants.X]
algo = "surf"
"""


def test_the_iqm_curves_are_over_runs_and_say_what_they_pool(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each run is one curve of the IQM, as each is one score of the primary table: a seed's
    runs at two eps are not averaged into one; and the one panel, which pools both eps, says
    so rather than naming the first."""
    from experiments import preregistered, report

    monkeypatch.setattr(preregistered, "REPS", 200)
    monkeypatch.setattr(preregistered, "CURVE_REPS", 50)
    folder = tmp_path / "two-eps"
    folder.mkdir()
    (folder / "spec.toml").write_text(TWO_EPS)
    for variant in "RX":
        for eps in (0.1, 0.3):
            for seed in range(4):
                run = folder / "dmc-cheetah_run" / variant / f"eps{eps:g}" / f"s{seed}"
                run.mkdir(parents=True)
                (run / "config.json").write_text(json.dumps(
                    {"algo": "pebble", "unsup_steps": 0,
                     "feedback": {"budget": 30, "selection": "disagreement"}}))
                # eps 0.1: 100 at every seed; eps 0.3: 0, but 500 at seed 3
                final = 100 if eps == 0.1 else 500 * (seed == 3)
                _write_csv(run / "eval.csv", "step,return", ["400,0", f"800,{final}"])
                (run / "done.json").write_text('{"step": 800}')
    results = load_results(folder)
    runs = preregistered.per_run(results)
    primary = preregistered.primary_table(results, runs).set_index("variant")
    bands = preregistered.iqm_bands(results, runs)
    # IQM of 0, 0, 0, 100, 100, 100, 100, 500: the mean of the middle half, 75.
    assert primary.loc["R", "iqm"] == pytest.approx(75.0)
    assert bands["R"].n == 8 and bands["R"].mean[-1] == pytest.approx(75.0)

    drawn: list[tuple[list[str], list[str], list[tuple[str, str]]]] = []
    real = report.grid_png

    def watched(panels, rows, cols, **kw):  # type: ignore[no-untyped-def]
        drawn.append((list(rows), list(cols), sorted(panels)))
        return real(panels, rows, cols, **kw)

    monkeypatch.setattr(report, "grid_png", watched)
    report.preregistered_sections(results, tmp_path)
    [(rows, cols, panels)] = drawn
    assert (rows, cols) == (["eps 0.1, 0.3 pooled"], ["dmc:cheetah_run"])
    assert panels == [(rows[0], cols[0])]


def test_a_finished_run_without_a_score_is_counted_as_not_scored(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """R's walker s1 finished but its eval.csv was lost: every table says it is left out of
    the averages, rather than calling the run finished and averaging without it; two tasks
    pool their runs, so the comparison counts runs over both."""
    from experiments import preregistered
    from experiments.tables import final_markdown, final_table

    monkeypatch.setattr(preregistered, "REPS", 200)
    folder = tmp_path / "two-tasks"
    folder.mkdir()
    (folder / "spec.toml").write_text(TWO_EPS.replace("eps = [0.1, 0.3]", "eps = [0.3]")
                                      .replace("seeds = [0, 1, 2, 3]", "seeds = [0, 1]")
                                      .replace('tasks = ["dmc:cheetah_run"]',
                                               'tasks = ["dmc:cheetah_run", "dmc:walker_run"]'))
    finals = {("R", "cheetah", 0): 10, ("R", "cheetah", 1): 20, ("R", "walker", 0): 30,
              ("X", "cheetah", 0): 1, ("X", "cheetah", 1): 2, ("X", "walker", 0): 3,
              ("X", "walker", 1): 4}
    for variant in "RX":
        for task in ("cheetah", "walker"):
            for seed in (0, 1):
                run = folder / f"dmc-{task}_run" / variant / "eps0.3" / f"s{seed}"
                run.mkdir(parents=True)
                (run / "config.json").write_text(json.dumps(
                    {"algo": "pebble", "unsup_steps": 0,
                     "feedback": {"budget": 30, "selection": "disagreement"}}))
                if (variant, task, seed) in finals:
                    _write_csv(run / "eval.csv", "step,return",
                               ["400,0", f"800,{finals[(variant, task, seed)]}"])
                (run / "done.json").write_text('{"step": 800}')
    results = load_results(folder)
    runs = preregistered.per_run(results)
    primary = preregistered.primary_table(results, runs)
    improvement = preregistered.improvement_table(results, runs)
    table = preregistered.primary_markdown(primary, improvement)
    # R: 4 finished; walker has one score, so one run of each task is scored (one run a
    # task resamples to itself: no interval).
    assert "| R | pebble | 4/4, 2 scored | 20.0 | 20.0 |" in table
    assert "| X | surf | 4/4 | 2.5 [" in table
    assert "| R | X | 2 vs 4 | 1.00 [" in table

    final = final_markdown(final_table(results), metaworld=False)
    assert "| R | pebble | 30.0 (n=1) | 2/2 | s1 done, no evaluation |" in final
    assert "| R | pebble | 15.0 ± 7.1 | 2/2 | – |" in final


OWN_SEEDS = """
name = "own-seeds"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1, 2, 3]

[variants.A]
algo = "pebble"

[variants.B]
algo = "surf"
seeds = [0, 1]
"""


def test_a_variant_with_its_own_seeds_is_complete_with_them(tmp_path: Path) -> None:
    """B plans 2 seeds and finished both: no table or curve note calls it short of the spec's
    4; A, one of whose 4 runs stopped at step 400, is."""
    folder = tmp_path / "own-seeds"
    folder.mkdir()
    (folder / "spec.toml").write_text(OWN_SEEDS)
    for variant, seeds in (("A", 4), ("B", 2)):
        for seed in range(seeds):
            run = folder / "dmc-cheetah_run" / variant / "eps0.3" / f"s{seed}"
            run.mkdir(parents=True)
            (run / "config.json").write_text(json.dumps(
                {"feedback": {"budget": 100, "selection": "disagreement"}}))
            stopped = (variant, seed) == ("A", 3)
            evals = [(200, 1.0), (400, 2.0)] + ([] if stopped else [(600, 3.0 + seed)])
            _write_csv(run / "eval.csv", "step,return", [f"{s},{r}" for s, r in evals])
            _write_csv(run / "rounds.csv", "step,round,labels_used,distinguishable_ratio",
                       ["200,0,50,0.5", f"400,1,100,{0.6 + 0.1 * seed}"])
            _write_csv(run / "episodes.csv", "step,episode,return,updates,reward_updates",
                       ["400,1,0,400,200"])
            if not stopped:
                (run / "done.json").write_text(json.dumps({"step": 600}))
    write_report(folder)
    out = folder / "report"
    queries = (out / "queries.md").read_text()
    assert "| 100 | 4.0 ± 1.0 (n=3) | 3.5 ± 0.7 |" in queries
    for name in ("distinguishability", "agent"):
        rows = [line for line in (out / f"{name}.md").read_text().splitlines()
                if line.startswith("| dmc:cheetah_run")]
        assert rows and not any("(n=" in line for line in rows), (name, rows)
    notes = [line for line in (out / "report.md").read_text().splitlines()
             if line.startswith("- dmc:cheetah_run")]
    assert notes and not any(": B:" in line for line in notes), notes


def test_bootstrap_intervals_are_the_same_on_every_call() -> None:
    """rliable resamples from NumPy's global generator whatever random_state it is given: a
    report's intervals must not depend on what drew from that generator before."""
    from experiments import preregistered

    scores = {"a": np.array([111.9, 165.2, 54.9, 89.4, 113.7, 103.6, 221.3])[:, None]}
    first = preregistered._bootstrap(scores, preregistered._iqm, 500)
    np.random.seed(123)
    np.random.random(7)  # other code drawing from the global generator in between
    outside = np.random.get_state()
    assert preregistered._bootstrap(scores, preregistered._iqm, 500) == first
    assert preregistered._bootstrap(scores, preregistered._mean, 500) != first
    # ... and the global generator is left where the caller had it.
    assert np.array_equal(np.random.get_state()[1], outside[1])


def test_a_variants_interval_does_not_move_as_another_variants_runs_finish() -> None:
    """PEBBLE's scores are the same in both tables; only S-EPOA, listed before it, has a
    run more: PEBBLE's interval must be the same."""
    from experiments import preregistered

    pebble = np.array([147.9, 227.7, 162.8, 180.3, 181.3, 138.6])[:, None]
    before = {"S-EPOA": np.array([111.9, 165.2, 54.9])[:, None], "PEBBLE": pebble}
    after = {"S-EPOA": np.array([111.9, 165.2, 54.9, 89.4])[:, None], "PEBBLE": pebble}
    for func in (preregistered._iqm, preregistered._mean):
        assert (preregistered._bootstrap(before, func, 300)["PEBBLE"]
                == preregistered._bootstrap(after, func, 300)["PEBBLE"]
                == preregistered._bootstrap({"PEBBLE": pebble}, func, 300)["PEBBLE"])


def test_a_grid_whose_query_selecting_runs_have_not_finished_reports_as_partial(
        tmp_path: Path, capsys) -> None:
    """Mid-grid, or after a release at a time limit: only the SAC arm is done."""
    from sepoa.cli import main

    folder = tmp_path / "midway"
    folder.mkdir()
    (folder / "spec.toml").write_text(NEW_SPEC)
    for variant in ("A", "S"):
        run = folder / "dmc-cheetah_run" / variant / "eps0.3" / "budget100" / "s0"
        run.mkdir(parents=True)
        (run / "config.json").write_text(json.dumps(
            {"feedback": {"budget": 100} | NEW_FEEDBACK[variant]}))
        _write_csv(run / "eval.csv", "step,return", ["200,1.0"])
        _write_csv(run / "episodes.csv", "step,episode,return", ["200,0,1.0"])
        if variant == "S":
            (run / "done.json").write_text(json.dumps({"step": 600}))
    assert main(["report", str(folder)]) == 0, capsys.readouterr().err
    index = (folder / "report" / "report.md").read_text()
    assert "No finished query-selecting run with a checkpoint.pt: Monte Carlo only." in index
    assert "6 planned: 1 done, 0 stopped, 1 partial, 0 failed, 4 not started." in index


def test_a_preregistered_grid_with_no_evaluation_yet_is_reported_as_partial(
        tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """Just enqueued: spec.toml and nothing else. The report says so, without a traceback."""
    from experiments import preregistered
    from sepoa.cli import main

    monkeypatch.setattr(preregistered, "REPS", 100)
    folder = tmp_path / "two-eps"
    folder.mkdir()
    (folder / "spec.toml").write_text(TWO_EPS)
    assert main(["report", str(folder)]) == 0, capsys.readouterr().err
    index = (folder / "report" / "report.md").read_text()
    assert "**Partial**: 0 of 16 planned runs finished (16 not started)" in index
    assert "| R | pebble | 0/8 | – | – |" in index


def _measured_quality(seed: int, skills: list[float], randoms: list[float]) -> dict:
    from trainer.skills import quality

    return {"format": quality.QUALITY_FORMAT, "task": "dmc:cheetah_run", "seed": seed,
            "skills": len(skills), "skill": quality.summary(skills),
            "random_actions": quality.summary(randoms), "skill_returns": skills,
            "random_action_returns": randoms, "best_skill": [0.0]}


def test_a_snapshots_quality_interval_does_not_move_as_others_join(tmp_path: Path) -> None:
    from experiments.skill_quality import quality_table
    from trainer.skills import quality

    skills, randoms = [float(r) for r in range(50)], [float(r % 7) for r in range(50)]
    paths = []
    for seed in (10, 11):
        path = tmp_path / f"dmc-cheetah_run-aps-1000000-s{seed}-abc-at100000.pt"
        quality.write(str(path), _measured_quality(seed, skills, randoms), 100_000)
        paths.append(Path(quality.quality_path(str(path))))
    alone = quality_table(paths[1:])
    both = quality_table(paths)
    pd.testing.assert_frame_equal(alone.iloc[[0]].reset_index(drop=True),
                                  both[both.seed == 11].reset_index(drop=True))


def test_the_grids_snapshots_skill_quality_is_reported_and_kept(results: Path,
                                                                 tmp_path: Path) -> None:
    """The table holds the snapshots the grid's runs start from, not another grid's in the same
    snapshots folder; `experiment keep` keeps their quality files, so the kept folder's report
    has the table too."""
    from experiments.keep import keep
    from experiments.spec import grid_snapshots, load_spec
    from trainer.skills import quality

    grid = tmp_path / "results" / "synthetic"
    shutil.copytree(results, grid, ignore=shutil.ignore_patterns("report"))
    (grid / "dmc-cheetah_run" / "B" / "eps0.3" / "budget100" / "s0" / "done.json").write_text(
        json.dumps({"step": 600}))
    spec = load_spec(grid / "spec.toml")
    ours = sorted(grid_snapshots(spec))
    assert len(ours) == 2 and all(name.endswith(".pt") for name in ours)  # one a seed
    snapshots = tmp_path / "results" / "snapshots"
    snapshots.mkdir()
    skills, randoms = [float(r) for r in range(50)], [1.0] * 49 + [3.0]
    seed = 0 if "-s0-" in ours[0] else 1
    quality.write(str(snapshots / ours[0]), _measured_quality(seed, skills, randoms), 600)
    quality.write(str(snapshots / "dmc-cheetah_run-aps-200000-s10-abc-at100000.pt"),
                  _measured_quality(10, skills, randoms), 100_000)  # another grid's
    write_report(grid)
    text = (grid / "report" / "report.md").read_text()
    assert "## Skill quality of the snapshots" in text
    # median 24.5, top-5 mean of 45..49 = 47, max 49; random: median 1, top-5 mean 1.4, max 3.
    assert f"| {seed} | 24.5 | 47.0 [" in text and "| 49.0 | 1.0 | 1.4 [" in text
    assert "| 100,000 | 10 |" not in text
    assert len(pd.read_csv(grid / "report" / "skill-quality.csv")) == 1

    kept = tmp_path / "kept"
    keep(spec, tmp_path / "results", kept)
    assert [p.name for p in (kept / "snapshots").iterdir()] == [
        quality.quality_path(ours[0])]
    write_report(kept)
    assert f"| {seed} | 24.5 | 47.0 [" in (kept / "report" / "report.md").read_text()


def test_a_grid_whose_rounds_asked_nothing_is_reported(tmp_path: Path, capsys) -> None:
    """Runs on the true reward (`reward.true_reward`) keep their rounds but ask no queries: their
    rounds.csv has no distinguishable ratio, and the report has no such figures, not a crash."""
    from sepoa.cli import main

    folder = tmp_path / "truth"
    folder.mkdir()
    (folder / "spec.toml").write_text(NEW_SPEC + """
[analysis]
metric = "final_quarter"
reference = "A"
compare_to = ["S"]
""")
    for variant in ("A", "S"):
        run = folder / "dmc-cheetah_run" / variant / "eps0.3" / "budget100" / "s0"
        run.mkdir(parents=True)
        (run / "config.json").write_text(json.dumps(
            {"algo": {"A": "pebble", "S": "sac"}[variant], "unsup_steps": 100,
             "feedback": {"budget": 100} | NEW_FEEDBACK[variant]}))
        _write_csv(run / "eval.csv", "step,return", ["200,1.0", "600,2.0"])
        _write_csv(run / "episodes.csv", "step,episode,return", ["600,0,2.0"])
        _write_csv(run / "rounds.csv", "step,round,queries,answered,answers,reward_corr",
                   ["200,0,0,0,0,1.0", "400,1,0,0,0,0.9"])
        (run / "done.json").write_text(json.dumps({"step": 600}))
    assert main(["report", str(folder)]) == 0, capsys.readouterr().err
    index = (folder / "report" / "report.md").read_text()
    assert "6 planned: 2 done, 0 stopped, 0 partial, 0 failed, 4 not started." in index
    assert "## Pre-registered comparison" in index


def test_the_report_says_how_long_the_grids_workers_ran(analysed: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A stop rule in wall time reads the grid's recorded training periods (sessions.csv)."""
    import shutil

    from experiments import preregistered

    assert "worked (" not in (analysed / "report" / "report.md").read_text()  # none recorded
    copy = tmp_path / "analysed"
    shutil.copytree(analysed, copy, ignore=shutil.ignore_patterns("report"))
    (copy / "sessions.csv").write_text(
        "started_at,ended_at,workers,threads,ended_by\n"
        "2026-11-28T08:00:00+00:00,2026-11-28T10:00:00+00:00,2,1,signal 15\n"
        "2026-11-28T12:00:00+00:00,2026-11-28T12:30:00+00:00,2,1,finished\n")
    monkeypatch.setattr(preregistered, "REPS", 300)
    monkeypatch.setattr(preregistered, "CURVE_REPS", 50)
    write_report(copy)
    index = (copy / "report" / "report.md").read_text()
    assert "worked (local workers' wall time, sessions.csv): 2h30m over 2 session(s)." in index
    assert "stop rule" not in index  # the spec has none
    # With a stop rule of 2 h, spent, that left seed 3 out (experiments.stop_rule's record):
    spec = (copy / "spec.toml").read_text()
    (copy / "spec.toml").write_text(spec.replace("seeds = [0, 1, 2, 3]\n",
                                                 "seeds = [0, 1, 2, 3]\nstop_after_hours = 2\n"))
    (copy / "stop_rule.json").write_text(json.dumps(
        {"hours": 2, "reached_at": "2026-11-28T12:30:00+00:00", "worked_s": 9000,
         "seeds_not_started": [3]}))
    write_report(copy)
    assert ("stop rule: no seed starts after 2 h of the workers' training; reached (2h30m "
            "spent): seeds not started: 3." in (copy / "report" / "report.md").read_text())

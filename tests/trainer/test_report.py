"""The report's numbers on hand-written results: final returns, the query-count and
distinguishability tables (sample std), curve alignment on unequal step grids, partial seeds,
and PNG figures."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from sepoa.plots import PNG_SIGNATURE, Band, align, curves_png
from trainer.experiments.report import curve_panels, mean_std, write_report
from trainer.experiments.results import load_results
from trainer.experiments.spec import SpecError

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
    from trainer.cli import main

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
    assert "Runs: 8 planned: 7 done, 1 partial, 0 failed, 0 not started." in index
    assert "- dmc:cheetah_run, eps 0.3: B: 2 of 2 seeds, up to step 400" in index
    res = load_results(results)
    assert len(res.runs) == 8 and set(res.evals["budget"]) == {100, 200}
    # The partial seed is in its curve, which stops at that seed's last evaluation.
    band = curve_panels(res, "return", ["dmc:cheetah_run"], 200)[("eps 0.3", "dmc:cheetah_run")]
    assert band["B"].steps.tolist() == [200, 400] and band["B"].n == 2
    assert band["A"].steps.tolist() == [200, 400, 600]


def test_report_of_a_folder_without_spec_is_an_error(tmp_path: Path, capsys) -> None:
    from trainer.cli import main

    assert main(["report", str(tmp_path)]) == 2
    assert "spec.toml: cannot read the spec" in capsys.readouterr().err
    with pytest.raises(SpecError):
        write_report(tmp_path)


def test_plots_draw_plain_data_without_torch() -> None:
    png = curves_png({"a": [([0, 1, 2], [0.0, 1.0, 2.0]), ([0, 2], [1.0, 3.0])],
                      "b": Band(np.array([0, 2]), np.array([1.0, 1.0]),
                                np.array([0.1, 0.1]), 3)}, title="t")
    assert png.startswith(PNG_SIGNATURE)
    probe = ("import sys, sepoa.plots; "
             "print('torch' in sys.modules, 'matplotlib.pyplot' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"]

"""Proposition 1: under its assumptions the ensemble's Var[P] falls as the return gap grows; on
a real trained ensemble the measured curve is a well-formed table of quantile bins."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from experiments.proposition import (
    binned,
    measured_disagreement,
    proposition_png,
    simulated_disagreement,
    spearman,
)
from experiments.report import write_report
from experiments.spec import load_spec
from figures.curves import PNG_SIGNATURE
from runvocab.config import build_config
from trainer.loop import TrainingRun

torch.set_num_threads(1)


@pytest.mark.parametrize("c", [0.5, 1.0, 4.0])
def test_monte_carlo_disagreement_falls_as_the_gap_grows(c: float) -> None:
    gaps = math.sqrt(c) * np.array([0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0])
    var = simulated_disagreement(gaps, c, samples=200_000, rng=np.random.default_rng(0))
    assert var.shape == gaps.shape and np.all(var > 0)
    assert np.all(np.diff(var) < 0)
    # Similar returns (gap 0) are far more disputed than clearly different ones.
    assert var[0] > 3 * var[-1]
    # c is a variance: the difference of two draws has variance 2c; at gap 0 the exact value
    # for c = 1 is 0.0684 (Gauss-Hermite quadrature).
    if c == 1.0:
        assert var[0] == pytest.approx(0.0684, abs=0.002)


def test_monte_carlo_is_reproducible_and_noisier_ensembles_disagree_more() -> None:
    gaps = np.array([0.0, 1.0, 2.0])
    a = simulated_disagreement(gaps, 1.0, samples=10_000, rng=np.random.default_rng(3))
    b = simulated_disagreement(gaps, 1.0, samples=10_000, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(a, b)
    small, large = (simulated_disagreement(gaps, c, rng=np.random.default_rng(0))
                    for c in (0.25, 4.0))
    assert np.all(large > small)


def test_spearman_ranks_with_ties() -> None:
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [9, 4, 1, 0]) == pytest.approx(-1.0)
    # ties take their average rank: ranks (1.5, 1.5, 3) and (1, 2, 3)
    assert spearman([5, 5, 7], [1, 2, 3]) == pytest.approx(np.corrcoef([1.5, 1.5, 3],
                                                                       [1, 2, 3])[0, 1])
    assert math.isnan(spearman([1, 1, 1], [1, 2, 3]))


def test_bins_are_quantiles_of_the_gap() -> None:
    gap = np.arange(8.0)
    table = binned(gap, 10 - gap, bins=4)
    assert table["pairs"].tolist() == [2, 2, 2, 2]
    assert table["gap_mid"].tolist() == [0.5, 2.5, 4.5, 6.5]
    assert table["var_p"].tolist() == [9.5, 7.5, 5.5, 3.5]
    # Tied edges (half the gaps are 0) leave a bin empty; it is dropped, no pair is lost.
    tied = binned(np.array([0.0, 0.0, 0.0, 0.0, 1.0, 2.0]), np.ones(6), bins=3)
    assert tied["pairs"].sum() == 6 and len(tied) < 3


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished tiny PEBBLE run (rounds at 400 and 800, so a trained reward ensemble)."""
    run_dir = tmp_path_factory.mktemp("tiny_run")
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "steps": 900, "threads": 1, "run_dir": str(run_dir)})
    TrainingRun(cfg, progress=False).train()
    return run_dir


def test_measured_disagreement_on_a_trained_ensemble(tiny_run: Path) -> None:
    measured = measured_disagreement(tiny_run, bins=5, pairs=3000, seed=1)
    table = measured.table
    assert list(table.columns) == ["gap_low", "gap_high", "gap_mid", "var_p", "pairs"]
    assert 1 <= len(table) <= 5 and table["pairs"].sum() == 3000
    assert np.all(np.diff(table["gap_mid"]) > 0) and np.all(np.diff(table["gap_low"]) >= 0)
    assert np.all(table["gap_low"] <= table["gap_mid"]) and np.all(
        table["gap_mid"] <= table["gap_high"])
    assert table["gap_low"].iloc[0] >= 0
    assert np.all(np.isfinite(table["var_p"])) and np.all(table["var_p"] >= 0)
    assert np.all(table["var_p"] <= 0.25)  # the variance of a value in [0, 1]
    assert -1 <= measured.spearman <= 1
    # The same seed draws the same pairs.
    again = measured_disagreement(tiny_run, bins=5, pairs=3000, seed=1)
    pd.testing.assert_frame_equal(table, again.table)
    png = proposition_png({1.0: ([0, 1, 2], simulated_disagreement([0, 1, 2], 1.0))},
                          {"pebble": table})
    assert png.startswith(PNG_SIGNATURE)


SPEC = """
name = "prop"
preset = "tiny"
steps = 900
tasks = ["dmc:cheetah_run"]
eps = [0.0]
seeds = [0]

[variants.P]
algo = "pebble"
"""


def test_report_draws_the_measured_curve_of_a_finished_run(tiny_run: Path,
                                                          tmp_path: Path) -> None:
    (tmp_path / "spec.toml").write_text(SPEC)
    (run,) = load_spec(tmp_path / "spec.toml", check=False).runs()
    shutil.copytree(tiny_run, tmp_path / run.dir)
    (tmp_path / run.dir / "done.json").write_text(json.dumps({"step": 900}))
    write_report(tmp_path)
    out = tmp_path / "report"
    assert (out / "proposition1.png").read_bytes().startswith(PNG_SIGNATURE)
    table = pd.read_csv(out / "proposition1.csv")
    assert table[["variant", "seed"]].values.tolist() == [["P", 0]]
    assert table["pairs"].iloc[0] > 0 and -1 <= table["spearman"].iloc[0] <= 1
    assert "| P | dmc:cheetah_run | 0 |" in (out / "report.md").read_text()

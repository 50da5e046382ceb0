"""Proposition 1 of the S-EPOA paper, demonstrated: ensemble disagreement grows as a pair's
true return gap shrinks.

The proposition: if each member's segment returns are r̂_j ~ N(r_j, c) (c a variance) and
P = sigmoid(r̂_1 − r̂_2), then Var[P] across the ensemble increases, approximately
monotonically, as the gap Δ = r_1 − r_2 ≥ 0 decreases. So the disagreement rule prefers pairs of
similar return, the ones a noisy teacher cannot tell apart. `simulated_disagreement` draws the
curve under exactly those assumptions; `measured_disagreement` draws it for a trained reward
ensemble on the segments of its own run's trajectory pool; `proposition_png` shows both.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike

from runvocab.config import load_json
from trainer.checkpoint import load_checkpoint
from trainer.query_selection import pool_rewards, preference_probabilities, sample_candidates
from trainer.reward_model import RewardModel
from trainer.trajectories import TrajectoryPool

COLUMNS = ["gap_low", "gap_high", "gap_mid", "var_p", "pairs"]


def simulated_disagreement(gaps: ArrayLike, c: float, samples: int = 200_000,
                           rng: np.random.Generator | None = None) -> np.ndarray:
    """Monte Carlo Var[sigmoid(r̂_1 − r̂_2)] with r̂_1 ~ N(Δ, c), r̂_2 ~ N(0, c), per gap Δ.
    Every gap reuses the same standard-normal draws (common random numbers), so the curve is
    smooth and its differences are not sampling noise."""
    rng = np.random.default_rng(0) if rng is None else rng
    noise = math.sqrt(c) * (rng.standard_normal(samples) - rng.standard_normal(samples))
    gaps = np.asarray(gaps, dtype=float)
    p = 1.0 / (1.0 + np.exp(-(gaps[:, None] + noise[None, :])))
    return p.var(axis=1)


def spearman(x: ArrayLike, y: ArrayLike) -> float:
    """Spearman's rank correlation (ties take their average rank); NaN if either is constant."""
    rx, ry = _ranks(np.asarray(x, dtype=float)), _ranks(np.asarray(y, dtype=float))
    if len(rx) < 2 or rx.std() == 0 or ry.std() == 0:
        return math.nan
    return float(np.corrcoef(rx, ry)[0, 1])


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    _, first, counts = np.unique(x[order], return_index=True, return_counts=True)
    ranks = np.empty(len(x))
    ranks[order] = np.repeat(first + (counts - 1) / 2, counts)
    return ranks


class Measured(NamedTuple):
    table: pd.DataFrame
    """a row per quantile bin of the true gap: gap_low, gap_high, gap_mid (the bin's median
    gap), var_p (mean disagreement of its pairs), pairs"""
    spearman: float
    """rank correlation of true gap and disagreement over all pairs (the proposition: < 0)"""


def measured_disagreement(run_dir: str | Path, bins: int = 8, pairs: int = 20_000,
                          seed: int = 0) -> Measured:
    """Disagreement against true gap for a finished run's reward ensemble: `pairs` random
    segment pairs of its pool (the run's segment length), Var[P] the population variance of
    P = sigmoid(r̂_1 − r̂_0) across members, the gap |difference of true segment returns|,
    binned by quantiles of the gap (bins of tied edges are left empty, then out)."""
    run_dir = Path(run_dir)
    cfg = load_json(str(run_dir / "config.json"))
    state = load_checkpoint(str(run_dir / "checkpoint.pt"))
    pool = TrajectoryPool(cfg.feedback.pool_trajectories)
    pool.load_state_dict(state["pool"])
    trajectories = list(pool.trajectories)
    h = cfg.feedback.segment_length
    lengths = np.array([t.length for t in trajectories])
    cands = sample_candidates(lengths, pairs, h, np.random.default_rng(seed))
    model = RewardModel(trajectories[0].obs.shape[1], trajectories[0].actions.shape[1],
                        cfg.reward, torch.device("cpu"), cfg.seed)
    model.load_state_dict(state["feedback"]["model"])
    rewards = pool_rewards(model, trajectories)
    p = preference_probabilities(rewards.sums(cands.traj0, cands.start0, h),
                                 rewards.sums(cands.traj1, cands.start1, h))
    var_p = p.double().var(dim=0, unbiased=False).numpy()
    true = np.concatenate([[0.0], np.cumsum(np.concatenate(
        [t.true_rewards for t in trajectories]), dtype=np.float64)])
    first0 = rewards.offsets[cands.traj0] + cands.start0
    first1 = rewards.offsets[cands.traj1] + cands.start1
    gap = np.abs((true[first1 + h] - true[first1]) - (true[first0 + h] - true[first0]))
    return Measured(binned(gap, var_p, bins), spearman(gap, var_p))


def binned(gap: np.ndarray, var_p: np.ndarray, bins: int) -> pd.DataFrame:
    """Pairs grouped by quantile bins of `gap`, in increasing order (see `Measured.table`)."""
    edges = np.quantile(gap, np.linspace(0, 1, bins + 1))
    which = np.searchsorted(edges[1:-1], gap, side="right")
    rows = [{"gap_low": edges[b], "gap_high": edges[b + 1],
             "gap_mid": float(np.median(gap[which == b])),
             "var_p": float(var_p[which == b].mean()), "pairs": int((which == b).sum())}
            for b in range(bins) if (which == b).any()]
    return pd.DataFrame(rows, columns=COLUMNS)


def proposition_png(simulated: Mapping[float, tuple[ArrayLike, ArrayLike]],
                    measured: Mapping[str, pd.DataFrame], dpi: int = 110) -> bytes:
    """Two panels, PNG bytes: left the Monte Carlo Var[P] per variance c against the gap,
    right each trained ensemble's mean Var[P] per bin against the bin's median true gap."""
    fig = Figure(figsize=(9.5, 3.8), layout="constrained")
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2, squeeze=True)
    for c, (gaps, var) in simulated.items():
        left.plot(np.asarray(gaps), np.asarray(var), lw=1.5, label=f"c = {c:g}")
    left.set_title("Monte Carlo: r̂ ~ N(r, c)", fontsize=9)
    left.set_xlabel("return gap Δ = r₁ − r₂", fontsize=9)
    for label, table in measured.items():
        right.plot(table["gap_mid"], table["var_p"], marker="o", ms=3, lw=1.5, label=label)
    right.set_title("trained reward ensembles, random segment pairs", fontsize=9)
    right.set_xlabel("true segment-return gap (bin median)", fontsize=9)
    if not measured:
        right.text(0.5, 0.5, "no finished run with a reward model", ha="center",
                   va="center", transform=right.transAxes, fontsize=9)
    for ax in (left, right):
        ax.set_ylabel("Var[P] across the ensemble", fontsize=9)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, frameon=False)
    fig.suptitle("Proposition 1: disagreement falls as the return gap grows", fontsize=11)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=dpi)
    return out.getvalue()

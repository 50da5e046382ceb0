"""Query selection: sample candidate segment pairs from the trajectory pool, score them, keep the
best. Rules: uniform, disagreement (spread of P across the ensemble), entropy (of P), and
S-EPOA's skill rule (see trainer/return_estimator.py).

Scoring touches each pooled transition once per round: the ensemble rewards every transition of
the pool in one pass, prefix sums per member give any segment's return as a difference, and the
pair statistics follow from those returns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from runvocab.names import SELECTION_MODES, SELECTION_RULES
from trainer.return_estimator import ReturnEstimator, skill_scores
from trainer.reward_model import RewardModel
from trainer.trajectories import Trajectory, stacked_skills

RULES, MODES = SELECTION_RULES, SELECTION_MODES
SCORING_CHUNK = 4096
"""transitions per ensemble forward pass when scoring the pool"""


@dataclass(frozen=True)
class Candidates:
    """Segment pairs as indices into the pool: trajectory and start step of each side."""

    traj0: np.ndarray
    start0: np.ndarray
    traj1: np.ndarray
    start1: np.ndarray

    def __len__(self) -> int:
        return len(self.traj0)

    def take(self, idx: np.ndarray) -> Candidates:
        return Candidates(self.traj0[idx], self.start0[idx], self.traj1[idx], self.start1[idx])


def sample_candidates(lengths: np.ndarray, n: int, segment_length: int,
                      rng: np.random.Generator) -> Candidates:
    """`n` pairs whose two segments come from different trajectories of the given lengths."""
    usable = np.flatnonzero(lengths >= segment_length)
    if len(usable) < 2:
        raise ValueError(
            f"need two trajectories of at least {segment_length} steps to form a query; "
            f"the pool has {len(usable)}"
        )
    a = rng.integers(0, len(usable), n)
    # Drawing the second from the other len-1 trajectories keeps the pair distinct and uniform.
    b = rng.integers(0, len(usable) - 1, n)
    b = b + (b >= a)
    traj0, traj1 = usable[a], usable[b]
    start0 = (rng.random(n) * (lengths[traj0] - segment_length + 1)).astype(np.int64)
    start1 = (rng.random(n) * (lengths[traj1] - segment_length + 1)).astype(np.int64)
    return Candidates(traj0, start0, traj1, start1)


def pool_inputs(pool: list[Trajectory]) -> tuple[np.ndarray, np.ndarray]:
    """Every transition of the pool as one (N, obs_dim + action_dim) array, and the offset of
    each trajectory's first transition in it."""
    lengths = np.array([t.length for t in pool])
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    inputs = np.concatenate([np.concatenate([t.obs, t.actions], axis=1) for t in pool])
    return inputs, offsets


@dataclass(frozen=True)
class PoolRewards:
    """Per-member prefix sums of the predicted reward over every pooled transition."""

    prefix: torch.Tensor
    """(E, N + 1) float64"""
    offsets: np.ndarray
    """index of each trajectory's first transition"""
    lengths: np.ndarray

    def sums(self, traj: np.ndarray, start: np.ndarray, length: int | np.ndarray) -> torch.Tensor:
        """Per-member predicted returns of the given spans: (E, n) float32."""
        first = torch.as_tensor(self.offsets[traj] + start, device=self.prefix.device)
        last = first + torch.as_tensor(length, device=self.prefix.device)
        return (self.prefix[:, last] - self.prefix[:, first]).float()

    def trajectory_returns(self) -> np.ndarray:
        """Ensemble-mean predicted return of each whole trajectory: (n_traj,)."""
        idx = np.arange(len(self.lengths))
        return self.sums(idx, np.zeros_like(idx), self.lengths).mean(0).cpu().numpy()


def pool_rewards(model: RewardModel, pool: list[Trajectory]) -> PoolRewards:
    """Score every pooled transition once (the ensemble's rewards, as prefix sums)."""
    inputs, offsets = pool_inputs(pool)
    with torch.inference_mode():
        # 4096 rows keep each layer's activations at ~12 MB: big chunks cost a fresh, page-
        # faulted allocation per layer (65 536 rows took ~1.6x as long on a 2-core CPU).
        rewards = model.member_rewards(torch.as_tensor(inputs, device=model.device),
                                       chunk=SCORING_CHUNK)
    prefix = torch.nn.functional.pad(rewards.double().cumsum(dim=1), (1, 0))  # (E, N + 1)
    return PoolRewards(prefix, offsets, np.array([t.length for t in pool]))


def segment_returns(model: RewardModel, pool: list[Trajectory], cands: Candidates,
                    segment_length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-member predicted returns of both sides of every candidate: two (E, n) tensors."""
    rewards = pool_rewards(model, pool)
    return (rewards.sums(cands.traj0, cands.start0, segment_length),
            rewards.sums(cands.traj1, cands.start1, segment_length))


def preference_probabilities(returns0: torch.Tensor, returns1: torch.Tensor) -> torch.Tensor:
    """P[seg1 > seg0] per member: (E, n)."""
    return torch.sigmoid(returns1 - returns0)


def disagreement(p: torch.Tensor) -> torch.Tensor:
    """Spread of P across the ensemble (population standard deviation): (n,)."""
    return p.std(dim=0, unbiased=False)


def entropy(p: torch.Tensor) -> torch.Tensor:
    """Mean over members of the binary entropy of P: (n,)."""
    p = p.clamp(1e-6, 1 - 1e-6)
    return -(p * p.log() + (1 - p) * (1 - p).log()).mean(0)


def top_k(scores: torch.Tensor, k: int) -> np.ndarray:
    return torch.topk(scores, min(k, len(scores))).indices.cpu().numpy()


def best_per_group(scores: torch.Tensor, groups: int) -> np.ndarray:
    """Index of the best of each of `groups` consecutive, equal groups of `scores`."""
    size = len(scores) // groups
    best = scores.view(groups, size).argmax(dim=1).cpu().numpy()
    return np.arange(groups) * size + best


@dataclass(frozen=True)
class Selection:
    queries: Candidates
    """the chosen pairs"""
    probability: np.ndarray
    """the model's mean P[seg1 > seg0] for each chosen pair (nan when the model was not used)"""
    score: np.ndarray
    """the selection score of each chosen pair (nan for uniform)"""
    candidate: np.ndarray
    """the index of each chosen pair in the round's draw of candidates"""


def select_queries(rule: str, model: RewardModel, pool: list[Trajectory], n_queries: int,
                   candidate_factor: int, segment_length: int, rng: np.random.Generator,
                   estimator: ReturnEstimator | None = None, spread: str = "var",
                   rewards: PoolRewards | None = None, mode: str = "top_k") -> Selection:
    """`n_queries` pairs by `rule` (uniform: random pairs). `mode` per_query: each query is the
    best of its own `candidate_factor` fresh random pairs (the paper's Algorithm 2); top_k: the
    best `n_queries` of one draw of `n_queries * candidate_factor`. Either way the round draws
    and scores the same number of candidates. The skill rule scores by the fitted `estimator`
    (R_theta) of each side's skill and the `spread` of P ("var" or "std"), min-max normalised
    over the candidates competing for a place. `rewards`: the pool already scored by `model`."""
    if rule not in RULES:
        raise ValueError(f"unknown selection rule {rule!r}; valid: {', '.join(RULES)}")
    if mode not in MODES:
        raise ValueError(f"unknown selection mode {mode!r}; valid: {', '.join(MODES)}")
    lengths = np.array([t.length for t in pool])
    if rule == "uniform":
        chosen = sample_candidates(lengths, n_queries, segment_length, rng)
        nan = np.full(len(chosen), np.nan)
        return Selection(chosen, nan, nan, np.arange(len(chosen)))
    cands = sample_candidates(lengths, n_queries * candidate_factor, segment_length, rng)
    groups = n_queries if mode == "per_query" else 1
    rewards = pool_rewards(model, pool) if rewards is None else rewards
    p = preference_probabilities(rewards.sums(cands.traj0, cands.start0, segment_length),
                                 rewards.sums(cands.traj1, cands.start1, segment_length))
    if rule == "skill":
        if estimator is None or not estimator.fitted or any(t.skill is None for t in pool):
            raise ValueError("the skill rule needs S-EPOA's fitted return estimator and "
                             "trajectories with skills (algo sepoa)")
        values = estimator.predict(stacked_skills(pool))
        idx0 = torch.as_tensor(cands.traj0, device=values.device)
        idx1 = torch.as_tensor(cands.traj1, device=values.device)
        # Scores normalised within each group of competing candidates.
        shape = (groups, len(cands) // groups)
        scores = skill_scores(values[idx0].view(shape), values[idx1].view(shape),
                              p.to(values.device).view(len(p), *shape), spread).reshape(-1)
    else:
        scores = disagreement(p) if rule == "disagreement" else entropy(p)
    idx = best_per_group(scores, n_queries) if mode == "per_query" else top_k(scores, n_queries)
    return Selection(cands.take(idx), p.mean(0).cpu().numpy()[idx], scores.cpu().numpy()[idx],
                     idx)

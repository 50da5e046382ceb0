"""What the skill-discovery backends share: the batch they read, the interface they offer, and
the kNN particle entropy that APS and CIC put into their intrinsic rewards."""

from __future__ import annotations

from collections.abc import Iterable
from typing import ClassVar, NamedTuple, Protocol

import numpy as np
import torch

from runvocab.config import SkillConfig
from trainer.entropy import RunningMeanStd
from trainer.sac import UpdateMetrics


class SkillBatch(NamedTuple):
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor
    skill: torch.Tensor
    """(batch, skill_dim): the skill the transition was collected with"""


class SkillBackend(Protocol):
    """One unsupervised skill-discovery method: its skill space, its own nets (features or a
    discriminator) and the intrinsic reward they give. The policy is a `SkillAgent`."""

    name: ClassVar[str]
    default_skill_dim: ClassVar[int]
    default_update_skill_every: ClassVar[int]
    successor_features: ClassVar[bool]
    """True: the agent's critic is APS's Q(s, a, z) = Psi(s, a, z)^T z"""
    skill_dim: int

    def __init__(self, obs_dim: int, cfg: SkillConfig, device: torch.device) -> None: ...

    def sample_skills(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """(n, skill_dim) float32 skills drawn from the method's prior p(z)."""
        ...

    def intrinsic_reward(self, batch: SkillBatch) -> torch.Tensor:
        """(batch, 1) reward, no gradient; updates the running kNN statistics where it has some."""
        ...

    def update(self, batch: SkillBatch) -> UpdateMetrics:
        """One gradient step of the backend's own nets."""
        ...

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


def particle_entropy(h: torch.Tensor, k: int, stats: RunningMeanStd | None = None,
                     clip: float = 0.0) -> torch.Tensor:
    """URLB's particle-based entropy reward of each row of `h` (batch, d) within the batch:
    log(1 + mean_j max(d_j / m - clip, 0)) over its k nearest rows j, itself included (at
    distance 0) as in URLB. m is the running mean of all kNN distances seen, this batch's
    included (`stats` is updated in place); without `stats`, m = 1. Returns (batch, 1)."""
    return knn_reward(torch.cdist(h, h, compute_mode="donot_use_mm_for_euclid_dist"), k, stats,
                      clip)


def knn_reward(dist: torch.Tensor, k: int, stats: RunningMeanStd | None = None,
               clip: float = 0.0) -> torch.Tensor:
    """`particle_entropy` from the rows' distances (batch, batch), however they were computed."""
    knn = dist.topk(k, dim=1, largest=False).values
    if stats is not None:
        stats.update(knn)
        knn = knn / stats.mean
    knn = (knn - clip).clamp_min(0.0)
    return torch.log1p(knn.mean(dim=1, keepdim=True))


def adam(params: Iterable[torch.Tensor], lr: float,
         device: torch.device) -> torch.optim.Adam:
    """Adam as SAC makes it: the fused kernel, one launch per step."""
    return torch.optim.Adam(params, lr=lr, fused=device.type in ("cuda", "cpu"))


def mean_metrics(rows: list[UpdateMetrics]) -> dict[str, float]:
    """Key-wise mean of update metrics (keys missing from some rows average over the others),
    each key's values read from the device at once."""
    values: dict[str, list[torch.Tensor]] = {}
    for row in rows:
        for key, value in row.items():
            values.setdefault(key, []).append(value)
    return {key: float(np.mean(torch.stack(v).cpu().numpy().astype(np.float64)))
            for key, v in values.items()}

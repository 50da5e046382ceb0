"""APS (Liu & Abbeel 2021) with a SAC backbone, as S-EPOA pretrains it.

Skills are unit vectors z in R^d (d = 10). A feature net phi(s) -> R^d, normalised to unit
length, is trained to maximise phi(s')^T z; the critic is the successor-feature critic
Q(s, a, z) = Psi(s, a, z)^T z. The intrinsic reward (the paper's appendix, with URLB's details):

    r = phi(s')^T z + beta * log(1 + mean over the k nearest of max(||h - h_j|| / m - c, 0))

with h the *unnormalised* feature of s' (as URLB computes the entropy term), the k nearest
neighbours taken within the batch, and m the running mean of those distances.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F

from runvocab.config import SkillConfig
from trainer.entropy import RunningMeanStd
from trainer.nets import mlp
from trainer.sac import UpdateMetrics
from trainer.skills.common import SkillBatch, adam, particle_entropy


class APS:
    name: ClassVar[str] = "aps"
    default_skill_dim: ClassVar[int] = 10
    default_update_skill_every: ClassVar[int] = 5
    successor_features: ClassVar[bool] = True

    def __init__(self, obs_dim: int, cfg: SkillConfig, device: torch.device):
        self.cfg, self.skill_dim = cfg, cfg.skill_dim
        self.features = mlp(obs_dim, self.skill_dim, cfg.hidden_dim, cfg.hidden_layers).to(device)
        self.opt = adam(self.features.parameters(), cfg.lr, device)
        self.entropy_stats = RunningMeanStd()

    def sample_skills(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Uniform on the unit sphere: normalised standard Gaussians."""
        z = rng.standard_normal((n, self.skill_dim))
        return (z / np.linalg.norm(z, axis=1, keepdims=True)).astype(np.float32)

    def phi(self, obs: torch.Tensor) -> torch.Tensor:
        """Unit-length state features, (batch, skill_dim)."""
        return F.normalize(self.features(obs), dim=-1)

    @torch.no_grad()
    def intrinsic_reward(self, batch: SkillBatch) -> torch.Tensor:
        h = self.features(batch.next_obs)
        entropy = particle_entropy(h, self.cfg.knn_k, self.entropy_stats, self.cfg.knn_clip)
        sf = (F.normalize(h, dim=-1) * batch.skill).sum(-1, keepdim=True)
        return sf + self.cfg.beta * entropy

    def update(self, batch: SkillBatch) -> UpdateMetrics:
        """One step on the feature loss -phi(s')^T z."""
        sf = (self.phi(batch.next_obs) * batch.skill).sum(-1).mean()
        loss = -sf
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return {"aps_loss": loss.detach()}

    def state_dict(self) -> dict:
        return {"features": self.features.state_dict(), "opt": self.opt.state_dict(),
                "entropy_stats": self.entropy_stats.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.features.load_state_dict(state["features"])
        self.opt.load_state_dict(state["opt"])
        self.entropy_stats.load_state_dict(state["entropy_stats"])

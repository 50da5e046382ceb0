"""CIC (Laskin et al. 2022) with a SAC backbone.

Skills are uniform in [0, 1]^d (d = 64). A contrastive discriminator scores a transition
tau = (s, s') against a skill: f(tau, z) = g1(tau)^T g2(z) / (|g1(tau)| |g2(z)| T), with
g1(tau) = pred_net([state_net(s), state_net(s')]) and g2 = skill_net. Its loss is InfoNCE over
the batch (the paper's log q(tau|z) = f(tau, z) - log mean_j exp f(tau_j, z), the other
transitions of the batch being the negatives). The intrinsic reward is the kNN particle entropy
of the transition embeddings g1(tau) within the batch, running-mean normalised. The critic is
SAC's own on [s, z].
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


class CIC:
    name: ClassVar[str] = "cic"
    default_skill_dim: ClassVar[int] = 64
    default_update_skill_every: ClassVar[int] = 50
    successor_features: ClassVar[bool] = False

    def __init__(self, obs_dim: int, cfg: SkillConfig, device: torch.device):
        self.cfg, self.skill_dim = cfg, cfg.skill_dim
        d, hidden, layers = self.skill_dim, cfg.hidden_dim, cfg.hidden_layers
        self.state_net = mlp(obs_dim, d, hidden, layers).to(device)
        self.pred_net = mlp(2 * d, d, hidden, layers).to(device)
        self.skill_net = mlp(d, d, hidden, layers).to(device)
        params = [*self.state_net.parameters(), *self.pred_net.parameters(),
                  *self.skill_net.parameters()]
        self.opt = adam(params, cfg.lr, device)
        self.entropy_stats = RunningMeanStd()

    def sample_skills(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Uniform in [0, 1]^skill_dim."""
        return rng.uniform(0.0, 1.0, (n, self.skill_dim)).astype(np.float32)

    def embed(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """Transition embeddings g1(s, s'), (batch, skill_dim), unnormalised."""
        return self.pred_net(torch.cat([self.state_net(obs), self.state_net(next_obs)], dim=-1))

    def logits(self, batch: SkillBatch) -> torch.Tensor:
        """(batch, batch): f(tau_j, z_i) for skill row i and transition column j."""
        query = F.normalize(self.skill_net(batch.skill), dim=-1)
        key = F.normalize(self.embed(batch.obs, batch.next_obs), dim=-1)
        return query @ key.T / self.cfg.temperature

    @torch.no_grad()
    def intrinsic_reward(self, batch: SkillBatch) -> torch.Tensor:
        key = self.embed(batch.obs, batch.next_obs)
        return particle_entropy(key, self.cfg.knn_k, self.entropy_stats, self.cfg.knn_clip)

    def update(self, batch: SkillBatch) -> UpdateMetrics:
        logits = self.logits(batch)
        target = torch.arange(len(logits), device=logits.device)
        loss = F.cross_entropy(logits, target)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        accuracy = (logits.detach().argmax(dim=1) == target).float().mean()
        return {"cic_loss": loss.detach(), "cic_accuracy": accuracy.detach()}

    def state_dict(self) -> dict:
        return {"state_net": self.state_net.state_dict(), "pred_net": self.pred_net.state_dict(),
                "skill_net": self.skill_net.state_dict(), "opt": self.opt.state_dict(),
                "entropy_stats": self.entropy_stats.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.state_net.load_state_dict(state["state_net"])
        self.pred_net.load_state_dict(state["pred_net"])
        self.skill_net.load_state_dict(state["skill_net"])
        self.opt.load_state_dict(state["opt"])
        self.entropy_stats.load_state_dict(state["entropy_stats"])

"""DIAYN (Eysenbach et al. 2019) with a SAC backbone, as URLB implements it.

Skills are one-hot vectors over d discrete skills (d = 16), drawn uniformly. A discriminator
q(z|s') (an MLP classifier on the next state) is trained by cross-entropy; the intrinsic reward
is log q(z|s') - log p(z) with p uniform, i.e. log q(z|s') + log d. The critic is SAC's own on
[s, z]; SAC's entropy term is DIAYN's H[A|S].
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F

from runvocab.config import SkillConfig
from trainer.nets import mlp
from trainer.sac import UpdateMetrics
from trainer.skills.common import SkillBatch, adam


class DIAYN:
    name: ClassVar[str] = "diayn"
    default_skill_dim: ClassVar[int] = 16
    default_update_skill_every: ClassVar[int] = 50
    successor_features: ClassVar[bool] = False

    def __init__(self, obs_dim: int, cfg: SkillConfig, device: torch.device):
        self.cfg, self.skill_dim = cfg, cfg.skill_dim
        self.discriminator = mlp(obs_dim, self.skill_dim, cfg.hidden_dim,
                                 cfg.hidden_layers).to(device)
        self.opt = adam(self.discriminator.parameters(), cfg.lr, device)

    def sample_skills(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """One-hot rows; each of the skill_dim skills equally likely."""
        z = np.zeros((n, self.skill_dim), np.float32)
        z[np.arange(n), rng.integers(self.skill_dim, size=n)] = 1.0
        return z

    def log_q(self, next_obs: torch.Tensor, skill: torch.Tensor) -> torch.Tensor:
        """log q(z|s') of each row's own skill, shape (batch,)."""
        log_probs = F.log_softmax(self.discriminator(next_obs), dim=-1)
        return log_probs.gather(1, skill.argmax(dim=1, keepdim=True)).squeeze(1)

    @torch.no_grad()
    def intrinsic_reward(self, batch: SkillBatch) -> torch.Tensor:
        return (self.log_q(batch.next_obs, batch.skill) + math.log(self.skill_dim)).unsqueeze(1)

    def update(self, batch: SkillBatch) -> UpdateMetrics:
        logits = self.discriminator(batch.next_obs)
        target = batch.skill.argmax(dim=1)
        loss = F.cross_entropy(logits, target)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        accuracy = (logits.detach().argmax(dim=1) == target).float().mean()
        return {"diayn_loss": loss.detach(), "diayn_accuracy": accuracy.detach()}

    def state_dict(self) -> dict:
        return {"discriminator": self.discriminator.state_dict(), "opt": self.opt.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.discriminator.load_state_dict(state["discriminator"])
        self.opt.load_state_dict(state["opt"])

"""The skill-conditioned agent pi(a|s,z): the project's SAC on [s, z], with APS's
successor-feature critic where the backend asks for it, and a replay buffer that keeps each
transition's skill."""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import nn

from runvocab.config import SACConfig
from trainer.nets import EnsembleMLP
from trainer.replay_buffer import ReplayBuffer
from trainer.sac import SAC, Batch, Critic, UpdateMetrics
from trainer.skills.common import SkillBatch


class SFCritic(nn.Module):
    """Q_i(s, a, z) = Psi_i(s, a, z)^T z for twin successor-feature heads Psi_1, Psi_2 (one
    ensemble). Takes `Critic`'s arguments, with the skill as the last `skill_dim` columns of
    `obs`; returns (2, batch, 1)."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig, skill_dim: int):
        super().__init__()
        self.skill_dim = skill_dim
        self.psi = EnsembleMLP(
            2, obs_dim + action_dim, skill_dim, cfg.hidden_dim, cfg.hidden_layers,
            init="orthogonal",
        )

    def forward(self, obs: torch.Tensor, action: torch.Tensor,
                detach_params: bool = False) -> torch.Tensor:
        psi = self.psi(torch.cat([obs, action], dim=-1), detach_params)  # (2, batch, skill_dim)
        return (psi * obs[:, -self.skill_dim:]).sum(-1, keepdim=True)


class SkillAgent:
    """pi(a|s,z) and its critic: a `SAC` whose observation is [s, z]."""

    def __init__(self, obs_dim: int, action_dim: int, skill_dim: int, cfg: SACConfig,
                 device: torch.device, successor_features: bool):
        self.obs_dim, self.action_dim, self.skill_dim = obs_dim, action_dim, skill_dim
        self.successor_features = successor_features
        factory = functools.partial(SFCritic, skill_dim=skill_dim) if successor_features else Critic
        self.sac = SAC(obs_dim + skill_dim, action_dim, cfg, device, factory)
        self.device = device

    def act(self, obs: np.ndarray, skill: np.ndarray, rng: np.random.Generator,
            deterministic: bool = False) -> np.ndarray:
        """One action in (-1, 1) for one observation under one skill."""
        return self.sac.act(np.concatenate([obs, skill], dtype=np.float32), rng, deterministic)

    def update(self, batch: SkillBatch) -> UpdateMetrics:
        """One SAC update on `batch.reward` (the caller puts the reward it trains on there)."""
        obs = torch.cat([batch.obs, batch.skill], dim=-1)
        next_obs = torch.cat([batch.next_obs, batch.skill], dim=-1)
        return self.sac.update(Batch(obs, batch.action, batch.reward, next_obs))

    def reset_critic(self) -> None:
        """A fresh critic, target and critic optimiser; the pretrained actor stays."""
        self.sac.reset_critic()

    @torch.no_grad()
    def q(self, obs: torch.Tensor, action: torch.Tensor, skill: torch.Tensor) -> torch.Tensor:
        """min over the twin critics of Q(s, a, z), shape (batch, 1)."""
        return self.sac.critic(torch.cat([obs, skill], dim=-1), action).min(dim=0).values

    def weights(self) -> dict:
        """What a snapshot keeps: the nets and the temperature, no optimiser state."""
        sac = self.sac
        return {
            "actor": sac.actor.state_dict(),
            "critic": sac.critic.state_dict(),
            "critic_target": sac.critic_target.state_dict(),
            "log_alpha": sac.log_alpha.detach().clone(),
        }

    def load_weights(self, weights: dict) -> None:
        """Loads `weights()` in place; the optimisers start fresh (fine-tuning has its own lr)."""
        sac = self.sac
        sac.actor.load_state_dict(weights["actor"])
        sac.critic.load_state_dict(weights["critic"])
        sac.critic_target.load_state_dict(weights["critic_target"])
        with torch.no_grad():
            sac.log_alpha.copy_(weights["log_alpha"])

    def state_dict(self) -> dict:
        return self.sac.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.sac.load_state_dict(state)


class SkillReplayBuffer(ReplayBuffer):
    """`ReplayBuffer` plus each transition's skill; `sample` returns a `SkillBatch`."""

    def __init__(self, obs_dim: int, action_dim: int, skill_dim: int, capacity: int,
                 device: torch.device, seed: int):
        super().__init__(obs_dim, action_dim, capacity, device, seed, skill_dim)
        (self.skill,) = self._fields[5:]  # the block after ReplayBuffer's five fields

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, true_reward: float,
            next_obs: np.ndarray, skill: np.ndarray | None = None) -> None:
        if skill is None:
            raise TypeError("SkillReplayBuffer.add needs the transition's skill")
        self._write([obs, action, next_obs, reward, true_reward, skill])

    def sample(self, batch_size: int) -> SkillBatch:  # type: ignore[override]
        idx = self.indices(batch_size)
        return SkillBatch(self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx],
                          self.skill[idx])

    def state_dict(self) -> dict:
        return super().state_dict() | {"skill": self.skill[: self.size].to("cpu", copy=True)}

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.skill[: state["size"]] = state["skill"].to(self.device)

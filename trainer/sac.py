"""Soft actor-critic with a squashed-Gaussian actor whose standard deviation is learned.

The two critics run as one ensemble (one batched matmul), the actor loss does not compute
critic weight gradients, and the target critic moves by one fused lerp: the update is the same
algorithm as the reference implementations, with less overhead per step.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from trainer.config import SACConfig
from trainer.nets import EnsembleMLP, NumpyMLP, mlp

LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


class Batch(NamedTuple):
    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor


class Actor(nn.Module):
    """pi(a|s): tanh-squashed Gaussian; mean and log-std both come from the network."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig):
        super().__init__()
        self.trunk = mlp(obs_dim, 2 * action_dim, cfg.hidden_dim, cfg.hidden_layers)
        self.log_std_min, self.log_std_max = cfg.log_std_min, cfg.log_std_max

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = self.trunk(obs).chunk(2, dim=-1)
        # Soft clamp into [min, max] keeps gradients alive at the bounds (pytorch_sac).
        log_std = torch.tanh(log_std)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (log_std + 1)
        return mean, log_std

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action in (-1, 1) and its log-probability, shape (batch, 1)."""
        mean, log_std = self(obs)
        noise = torch.randn_like(mean)
        u = mean + noise * log_std.exp()
        action = torch.tanh(u)
        # log N(u) - log|d tanh(u)/du|, the latter as 2(log 2 - u - softplus(-2u)) for stability.
        log_prob = -0.5 * noise.pow(2) - log_std - LOG_SQRT_2PI
        log_prob = log_prob - 2 * (math.log(2) - u - F.softplus(-2 * u))
        return action, log_prob.sum(-1, keepdim=True)


class Critic(nn.Module):
    """Two Q-functions Q_i(s, a) evaluated together: returns (2, batch, 1)."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig):
        super().__init__()
        self.q = EnsembleMLP(
            2, obs_dim + action_dim, 1, cfg.hidden_dim, cfg.hidden_layers, init="orthogonal"
        )

    def forward(self, obs: torch.Tensor, action: torch.Tensor, detach_params: bool = False):
        return self.q(torch.cat([obs, action], dim=-1), detach_params)


def _adam(params, cfg: SACConfig, device: torch.device) -> torch.optim.Adam:
    # The fused kernel is one launch per step instead of one per parameter.
    fused = device.type in ("cuda", "cpu")
    return torch.optim.Adam(params, lr=cfg.lr, betas=cfg.betas, fused=fused)


class SAC:
    """Actor, twin critics, target critics and a learned temperature, updated by `update`."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig, device: torch.device):
        self.cfg, self.device = cfg, device
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.actor = Actor(obs_dim, action_dim, cfg).to(device)
        self.critic = Critic(obs_dim, action_dim, cfg).to(device)
        self.critic_target = Critic(obs_dim, action_dim, cfg).to(device)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(cfg.init_temperature), device=device)
        self.log_alpha.requires_grad_(True)
        self.target_entropy = -float(action_dim)
        self.actor_opt = _adam(self.actor.parameters(), cfg, device)
        self.critic_opt = _adam(self.critic.parameters(), cfg, device)
        self.alpha_opt = _adam([self.log_alpha], cfg, device)
        self.updates = 0
        self._numpy_actor = NumpyMLP(list(self.actor.trunk)) if device.type == "cpu" else None

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def act(self, obs: np.ndarray, rng: np.random.Generator, deterministic: bool = False):
        """One action for one observation (the environment loop's hot path)."""
        if self._numpy_actor is None:
            obs_t = torch.as_tensor(obs, dtype=torch.float32, device=self.device).unsqueeze(0)
            with torch.no_grad():
                mean, log_std = (t[0].cpu().numpy() for t in self.actor(obs_t))
        else:
            mean, log_std = np.split(self._numpy_actor(obs), 2)
            log_std = np.tanh(log_std)
            lo, hi = self.cfg.log_std_min, self.cfg.log_std_max
            log_std = lo + 0.5 * (hi - lo) * (log_std + 1)
        if deterministic:
            return np.tanh(mean)
        return np.tanh(mean + rng.standard_normal(mean.shape, np.float32) * np.exp(log_std))

    def update(self, batch: Batch) -> dict[str, float]:
        metrics = self._update_critic(batch)
        if self.updates % self.cfg.actor_update_every == 0:
            metrics |= self._update_actor_and_alpha(batch.obs)
        if self.updates % self.cfg.target_update_every == 0:
            self._update_target()
        self.updates += 1
        return metrics

    def _update_critic(self, batch: Batch) -> dict[str, float]:
        with torch.no_grad():
            next_action, next_log_prob = self.actor.sample(batch.next_obs)
            target_q = self.critic_target(batch.next_obs, next_action).min(dim=0).values
            # No terminal states: DMControl and Metaworld episodes end only by time limit.
            target = batch.reward + self.cfg.gamma * (target_q - self.alpha * next_log_prob)
        q = self.critic(batch.obs, batch.action)
        loss = (q - target).pow(2).mean(dim=(1, 2)).sum()
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        return {"critic_loss": loss.item(), "q": q.detach().mean().item()}

    def _update_actor_and_alpha(self, obs: torch.Tensor) -> dict[str, float]:
        action, log_prob = self.actor.sample(obs)
        q = self.critic(obs, action, detach_params=True).min(dim=0).values
        alpha = self.alpha.detach()
        actor_loss = (alpha * log_prob - q).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()

        alpha_loss = (self.alpha * (-log_prob.detach() - self.target_entropy)).mean()
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_opt.step()
        return {
            "actor_loss": actor_loss.item(),
            "alpha": alpha.item(),
            "entropy": -log_prob.detach().mean().item(),
        }

    @torch.no_grad()
    def _update_target(self) -> None:
        torch._foreach_lerp_(
            list(self.critic_target.parameters()), list(self.critic.parameters()), self.cfg.tau
        )

    def reset_critic(self) -> None:
        """PEBBLE's critic reset after unsupervised pretraining: fresh critic, target and optimiser."""
        fresh = Critic(self.obs_dim, self.action_dim, self.cfg).to(self.device)
        self.critic.load_state_dict(fresh.state_dict())
        self.critic_target.load_state_dict(fresh.state_dict())
        self.critic_opt = _adam(self.critic.parameters(), self.cfg, self.device)

    def state_dict(self) -> dict:
        return {
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        self.actor.load_state_dict(state["actor"])
        self.critic.load_state_dict(state["critic"])
        self.critic_target.load_state_dict(state["critic_target"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.updates = state["updates"]

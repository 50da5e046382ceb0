"""Soft actor-critic with a squashed-Gaussian actor whose standard deviation is learned.

The two critics run as one ensemble (one batched matmul), the actor loss does not compute
critic weight gradients, and the target critic moves by one fused lerp: the update is the same
algorithm as the reference implementations, with less overhead per step.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from runvocab.config import SACConfig
from trainer.graphed_update import GraphedUpdate, Metrics
from trainer.nets import EnsembleMLP, NumpyMLP, mlp

LOG_SQRT_2PI = 0.5 * math.log(2 * math.pi)


UpdateMetrics = Metrics
"""an update's metrics, 0-d tensors on the training device (read when a row is logged)"""


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
        # Soft clamp into [min, max] keeps gradients alive at the bounds (pytorch_sac):
        # min + (max - min) * (tanh + 1) / 2, written as one multiply and one add.
        half = 0.5 * (self.log_std_max - self.log_std_min)
        log_std = torch.tanh(log_std).mul(half).add_(self.log_std_min + half)
        return mean, log_std

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action in (-1, 1) and its log-probability, shape (batch, 1)."""
        mean, log_std = self(obs)
        noise = torch.randn_like(mean)
        u = torch.addcmul(mean, noise, log_std.exp())
        action = torch.tanh(u)
        # log N(u) - log|d tanh(u)/du|, the latter as 2(log 2 - u - softplus(-2u)) for stability.
        # Per dimension: -noise^2 / 2 - log_std + 2(u + softplus(-2u)); the constants
        # -log sqrt(2 pi) - 2 log 2 are added once per row, after the sum (fewer ops per update).
        log_prob = torch.addcmul(2 * (u + F.softplus(-2 * u)) - log_std, noise, noise, value=-0.5)
        const = mean.shape[-1] * (LOG_SQRT_2PI + 2 * math.log(2))
        return action, log_prob.sum(-1, keepdim=True) - const


ACTION_BOUND = 1.0 - 1e-6
"""URLB's truncated normal keeps actions inside (-1, 1) by this much"""


def truncated(x: torch.Tensor) -> torch.Tensor:
    """URLB's truncated normal's clamp: the value inside the bounds, the gradient passed
    straight through, so the mean of an action at a bound still learns."""
    return x - x.detach() + x.detach().clamp(-ACTION_BOUND, ACTION_BOUND)


class FixedStdActor(Actor):
    """URLB's DDPG actor, as S-EPOA's authors fine-tune with it: the action is tanh of the
    trunk's mean plus Gaussian noise of a fixed `std`, clipped at `clip` (acting leaves it
    unclipped), kept within the bounds by `truncated`. Its log-probability (of a plain Gaussian
    at the bounded action, as URLB's truncated normal computes it) does not depend on the
    actor's weights, so an entropy term gives the actor no gradient: the temperature, tuned as
    SAC tunes it, only shifts the critic's target."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig, std: float, clip: float):
        super().__init__(obs_dim, action_dim, cfg)
        self.std, self.clip = std, clip

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        mean = torch.tanh(self.trunk(obs).chunk(2, dim=-1)[0])
        noise = (torch.randn_like(mean) * self.std).clamp(-self.clip, self.clip)
        action = truncated(mean + noise)
        z = (action - mean).detach() / self.std  # no gradient reaches it, as in URLB
        log_prob = -0.5 * z * z - math.log(self.std) - LOG_SQRT_2PI
        return action, log_prob.sum(-1, keepdim=True)


class Critic(nn.Module):
    """Two Q-functions Q_i(s, a) evaluated together: returns (2, batch, 1)."""

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig):
        super().__init__()
        self.q = EnsembleMLP(
            2, obs_dim + action_dim, 1, cfg.hidden_dim, cfg.hidden_layers, init="orthogonal"
        )

    def forward(self, obs: torch.Tensor, action: torch.Tensor,
                detach_params: bool = False) -> torch.Tensor:
        return self.q(torch.cat([obs, action], dim=-1), detach_params)


def _adam(params: Iterable[torch.Tensor], cfg: SACConfig, device: torch.device,
          capturable: bool = False) -> torch.optim.Adam:
    # The fused kernel is one launch per step instead of one per parameter; a capturable one
    # keeps its step count on the device, so a CUDA graph can replay it.
    fused = device.type in ("cuda", "cpu")
    return torch.optim.Adam(params, lr=cfg.lr, betas=cfg.betas, fused=fused,
                            capturable=capturable)


CriticFactory = Callable[[int, int, SACConfig], nn.Module]


class SAC:
    """Actor, twin critics, target critics and a learned temperature, updated by `update`.

    `critic_factory(obs_dim, action_dim, cfg)` swaps in another critic whose forward has
    `Critic`'s signature and output shape (2, batch, 1): APS's successor-feature critic.
    `graph_ready` runs every update through trainer/graphed_update.py's static batch and
    capturable optimisers (by default where `cfg.cuda_graph` is set on a CUDA device), captured
    in CUDA graphs on a GPU and run eagerly elsewhere.
    """

    def __init__(self, obs_dim: int, action_dim: int, cfg: SACConfig, device: torch.device,
                 critic_factory: CriticFactory = Critic, graph_ready: bool | None = None):
        self.cfg, self.device = cfg, device
        if device.type == "cuda":
            # Set either way, so a run gets what its config says whatever ran before it here.
            torch.backends.cuda.matmul.allow_tf32 = cfg.tf32
        self.obs_dim, self.action_dim = obs_dim, action_dim
        self.critic_factory = critic_factory
        self.actor = Actor(obs_dim, action_dim, cfg).to(device)
        self.critic = critic_factory(obs_dim, action_dim, cfg).to(device)
        self.critic_target = critic_factory(obs_dim, action_dim, cfg).to(device)
        self.critic_target.load_state_dict(self.critic.state_dict())
        self.critic_target.requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(cfg.init_temperature), device=device)
        self.log_alpha.requires_grad_(True)
        self.target_entropy = -float(action_dim)
        if graph_ready is None:
            graph_ready = cfg.cuda_graph and device.type == "cuda"
        self.actor_opt = _adam(self.actor.parameters(), cfg, device, graph_ready)
        self.critic_opt = _adam(self.critic.parameters(), cfg, device, graph_ready)
        self.alpha_opt = _adam([self.log_alpha], cfg, device, graph_ready)
        self.updates = 0
        # In-place loads and resets keep these the same tensors, so the lists stay valid.
        self._critic_params: list[torch.Tensor] = list(self.critic.parameters())
        self._target_params: list[torch.Tensor] = list(self.critic_target.parameters())
        self._numpy_actor = NumpyMLP(list(self.actor.trunk)) if device.type == "cpu" else None
        self._obs_pinned = (torch.empty(1, obs_dim, pin_memory=True)
                            if device.type == "cuda" else None)
        self.graphed: GraphedUpdate[Batch] | None = None
        if graph_ready:
            self.graphed = GraphedUpdate(
                self.step, lambda: (self.actor_opt, self.critic_opt, self.alpha_opt),
                capture=device.type == "cuda")

    @property
    def capturable(self) -> bool:
        """Whether the optimisers are built capturable: exactly when updates are graph-ready."""
        return self.graphed is not None

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    def act(self, obs: np.ndarray, rng: np.random.Generator,
            deterministic: bool = False) -> np.ndarray:
        """One action for one observation (the environment loop's hot path)."""
        d = self.action_dim
        if self._numpy_actor is None:
            # One wait for the device a step: the observation goes in asynchronously and the
            # trunk's output comes back in one copy. The rest is a few host flops, which as
            # kernels would cost more to launch than to run.
            with torch.no_grad():
                out = self.actor.trunk(self._obs_on_device(obs))[0].cpu().numpy()
        else:
            out = self._numpy_actor(obs)
        mean, log_std = out[:d], out[d:]
        # Actor.forward's soft clamp, in the same multiply-add form.
        half = 0.5 * (self.cfg.log_std_max - self.cfg.log_std_min)
        log_std = np.tanh(log_std) * half + (self.cfg.log_std_min + half)
        if isinstance(self.actor, FixedStdActor):
            if deterministic:
                return np.tanh(mean)
            noise = rng.standard_normal(self.action_dim, np.float32) * self.actor.std
            return np.clip(np.tanh(mean) + noise, -ACTION_BOUND, ACTION_BOUND)
        if deterministic:
            return np.tanh(mean)
        return np.tanh(mean + rng.standard_normal(self.action_dim, np.float32) * np.exp(log_std))

    def _obs_on_device(self, obs: np.ndarray) -> torch.Tensor:
        """(1, obs_dim) on the device, copied without waiting. On CUDA through one pinned
        buffer: `act` waits for the device before it returns, so the previous copy from it
        is done by the time it is overwritten."""
        if self._obs_pinned is None:
            return torch.from_numpy(np.asarray(obs, np.float32)).to(self.device).unsqueeze(0)
        self._obs_pinned.numpy()[0] = obs
        return self._obs_pinned.to(self.device, non_blocking=True)

    def update(self, batch: Batch) -> UpdateMetrics:
        """One update; its metrics stay on the device as 0-d tensors, read (one host sync each)
        only when a row is logged: reading five per update cost five device syncs."""
        slot = self.schedule()
        if self.graphed is not None:
            metrics = self.graphed(batch, slot)
        else:
            metrics = self.step(batch, *slot)
        self.updates += 1
        return metrics

    def schedule(self) -> tuple[bool, bool]:
        """Whether this update steps the actor and temperature, and whether the target."""
        return (self.updates % self.cfg.actor_update_every == 0,
                self.updates % self.cfg.target_update_every == 0)

    def step(self, batch: Batch, actor: bool, target: bool) -> UpdateMetrics:
        """The update's arithmetic, with no host sync and no branch on a tensor's value (what
        a CUDA graph can capture)."""
        # log_alpha changes only at the end of the update, so one exp serves all three losses.
        alpha = self.log_alpha.exp()
        metrics = self._update_critic(batch, alpha.detach())
        if actor:
            metrics |= self._update_actor_and_alpha(batch.obs, alpha)
        if target:
            self._update_target()
        return metrics

    def _update_critic(self, batch: Batch, alpha: torch.Tensor) -> UpdateMetrics:
        with torch.no_grad():
            next_action, next_log_prob = self.actor.sample(batch.next_obs)
            target_q = self.critic_target(batch.next_obs, next_action).min(dim=0).values
            # No terminal states: DMControl and Metaworld episodes end only by time limit.
            soft_q = torch.addcmul(target_q, alpha, next_log_prob, value=-1)  # Q' - alpha log pi
            target = torch.add(batch.reward, soft_q, alpha=self.cfg.gamma)
        q = self.critic(batch.obs, batch.action)
        # The sum over both critics of each one's mean squared error.
        loss = F.mse_loss(q, target.expand_as(q), reduction="sum") / len(target)
        self.critic_opt.zero_grad(set_to_none=True)
        loss.backward()
        self.critic_opt.step()
        return {"critic_loss": loss.detach(), "q": q.detach().mean()}

    def _update_actor_and_alpha(self, obs: torch.Tensor,
                                alpha: torch.Tensor) -> UpdateMetrics:
        action, log_prob = self.actor.sample(obs)
        q = self.critic(obs, action, detach_params=True).min(dim=0).values
        actor_loss = (alpha.detach() * log_prob - q).mean()
        mean_log_prob = log_prob.detach().mean()
        alpha_loss = alpha * (-mean_log_prob - self.target_entropy)
        # Each loss sees the other's parameters detached, so one backward pass through their
        # sum gives exactly the two separate gradients.
        self.actor_opt.zero_grad(set_to_none=True)
        self.alpha_opt.zero_grad(set_to_none=True)
        (actor_loss + alpha_loss).backward()
        self.actor_opt.step()
        self.alpha_opt.step()
        return {"actor_loss": actor_loss.detach(), "alpha": alpha.detach(),
                "entropy": -mean_log_prob}

    @torch.no_grad()
    def _update_target(self) -> None:
        torch._foreach_lerp_(self._target_params, self._critic_params, self.cfg.tau)

    def fix_actor_std(self, std: float, clip: float, alpha: float) -> None:
        """From now on act and learn with `FixedStdActor` (the same weights; the log-std half
        of the trunk's output goes unused), the temperature tuned from `alpha`."""
        fixed = FixedStdActor(self.obs_dim, self.action_dim, self.cfg, std, clip).to(self.device)
        fixed.load_state_dict(self.actor.state_dict())
        self.actor = fixed
        self.actor_opt = _adam(self.actor.parameters(), self.cfg, self.device, self.capturable)
        self._numpy_actor = (NumpyMLP(list(self.actor.trunk)) if self.device.type == "cpu"
                             else None)
        with torch.no_grad():
            self.log_alpha.fill_(math.log(alpha))
        if self.graphed is not None:
            self.graphed.forget()

    def reset_critic(self) -> None:
        """PEBBLE's critic reset after unsupervised pretraining: fresh critic, target and
        optimiser."""
        fresh = self.critic_factory(self.obs_dim, self.action_dim, self.cfg).to(self.device)
        self.critic.load_state_dict(fresh.state_dict())
        self.critic_target.load_state_dict(fresh.state_dict())
        self.critic_opt = _adam(self.critic.parameters(), self.cfg, self.device, self.capturable)
        if self.graphed is not None:
            self.graphed.forget()  # its graphs step the old optimiser's state

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
        for opt in (self.actor_opt, self.critic_opt, self.alpha_opt):
            for group in opt.param_groups:  # a loaded group says how the saving run stepped
                group["capturable"] = self.capturable
        self.updates = state["updates"]
        if self.graphed is not None:
            self.graphed.forget()  # the optimisers' state tensors were replaced

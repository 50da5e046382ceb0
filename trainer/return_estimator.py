"""S-EPOA's trajectory-return estimator R_theta(z) and the skill-based selection score.

R_theta(z) predicts how well the policy does under skill z: an ensemble of MLPs (skill -> tanh)
regressed by MSE onto each pooled trajectory's summed *predicted* reward r_hat (the labels are
the only reward signal there is), min-max normalised to [0, 1] over the pool. It is retrained
before each feedback round, and gives

- the selection score of a candidate pair from trajectories with skills (z0, z1):
  I = (1 + minmax |mean R_theta(z0) - mean R_theta(z1)|) * (1 + minmax spread of P),
  P being the reward ensemble's preference probabilities, its spread their variance (the
  paper) or standard deviation (the authors' code), both min-max normalised over the
  candidates: pairs whose skills promise clearly different returns *and* whose label the
  reward model is unsure of;
- z_task = argmax of mean R_theta over N_z fresh random skills: the skill the agent acts with.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from runvocab.config import SkillConfig
from runvocab.names import SCORE_SPREADS
from trainer.nets import EnsembleMLP
from trainer.skills.agent import SkillReplayBuffer

RewardFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""r_hat of (obs, action) rows: (n,)"""

SPREADS = SCORE_SPREADS


def minmax(x: torch.Tensor) -> torch.Tensor:
    """x scaled to [0, 1] along its last dimension; zeros where a row is constant."""
    low = x.amin(dim=-1, keepdim=True)
    span = x.amax(dim=-1, keepdim=True) - low
    return torch.where(span > 0, (x - low) / span.clamp(min=torch.finfo(x.dtype).tiny), 0.0)


def skill_scores(value0: torch.Tensor, value1: torch.Tensor, p: torch.Tensor,
                 spread: str) -> torch.Tensor:
    """I for candidates: R_theta means of both sides (..., n), preference probabilities
    (E, ..., n); each row of n competing candidates is min-max normalised on its own."""
    if spread not in SPREADS:
        raise ValueError(f"unknown spread {spread!r}; valid: {', '.join(SPREADS)}")
    s = p.var(dim=0, unbiased=False) if spread == "var" else p.std(dim=0, unbiased=False)
    return (1 + minmax((value0 - value1).abs())) * (1 + minmax(s))


class ReplayEpisodes:
    """R_theta's data as the authors' code takes it: every complete episode in the replay buffer
    (its skill, and its summed reward), not only the query pool's. Episodes are exactly
    `episode_length` transitions, stored in order, so episode i is rows [i L, (i + 1) L) as
    long as the ring has not wrapped; after that, with a capacity that is a multiple of L, the
    same blocks, less the one being overwritten."""

    def __init__(self, buffer: SkillReplayBuffer, episode_length: int):
        self.buffer, self.length = buffer, episode_length

    def blocks(self) -> list[int]:
        """The first row of each complete episode held."""
        b, n = self.buffer, self.length
        if b.size < b.capacity:
            return list(range(0, b.size // n * n, n))
        if b.capacity % n:  # a wrapped ring whose rows no longer line up with episodes
            raise ValueError(f"skill.estimator_data replay needs replay_capacity "
                             f"{b.capacity} to be a multiple of the episode length {n}")
        return [start for start in range(0, b.capacity, n)
                if not start < b.cursor < start + n]

    @torch.no_grad()
    def skills_and_returns(self, reward_fn: RewardFn | None) -> tuple[np.ndarray, np.ndarray]:
        """Each complete episode's skill and summed reward: `reward_fn(obs, action)` (the
        current r_hat), or the true reward where it is None."""
        b, n = self.buffer, self.length
        starts = self.blocks()
        if not starts:
            raise ValueError("R_theta has no complete episode in the replay buffer to fit on")
        skills = torch.stack([b.skill[start] for start in starts]).cpu().numpy()
        sums = []
        for start in starts:
            rows = slice(start, start + n)
            reward = (b.true_reward[rows, 0] if reward_fn is None
                      else reward_fn(b.obs[rows], b.action[rows]))
            sums.append(float(reward.double().sum()))
        return skills, np.array(sums)


class ReturnEstimator:
    """R_theta(z): an ensemble of `cfg.estimator_ensemble` MLPs, skill -> tanh output."""

    def __init__(self, skill_dim: int, cfg: SkillConfig, device: torch.device):
        self.cfg, self.device = cfg, device
        self.nets = EnsembleMLP(cfg.estimator_ensemble, skill_dim, 1, cfg.estimator_hidden_dim,
                                cfg.estimator_hidden_layers, output_activation=nn.Tanh).to(device)
        self.opt = torch.optim.Adam(self.nets.parameters(), lr=cfg.estimator_lr)
        self.fitted = False

    def fit(self, skills: np.ndarray, predicted_returns: np.ndarray) -> dict[str, float]:
        """Regress the min-max normalised `predicted_returns` (n,) on `skills` (n, d)."""
        z = torch.as_tensor(skills, dtype=torch.float32, device=self.device)
        target = minmax(torch.as_tensor(predicted_returns, dtype=torch.float32,
                                        device=self.device))
        loss = torch.zeros(())
        for _ in range(self.cfg.estimator_steps):  # full batch: a pool is at most ~100 rows
            loss = F.mse_loss(self.nets(z)[..., 0], target.expand(self.nets.n, -1))
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
        self.fitted = True
        return {"estimator_loss": loss.item()}

    @torch.no_grad()
    def predict(self, skills: np.ndarray) -> torch.Tensor:
        """Ensemble-mean R_theta of each skill: (n,)."""
        z = torch.as_tensor(skills, dtype=torch.float32, device=self.device)
        return self.nets(z)[..., 0].mean(0)

    def best_skill(self, candidates: np.ndarray) -> np.ndarray:
        """z_task: the candidate skill with the highest predicted return."""
        return candidates[int(self.predict(candidates).argmax())]

    def state_dict(self) -> dict:
        return {"nets": self.nets.state_dict(), "opt": self.opt.state_dict(),
                "fitted": self.fitted}

    def load_state_dict(self, state: dict) -> None:
        self.nets.load_state_dict(state["nets"])
        self.opt.load_state_dict(state["opt"])
        self.fitted = state["fitted"]

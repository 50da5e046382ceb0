"""Which reward the agent trains on.

- The SAC oracle: the environment's true reward.
- The preference-learning algorithms, before their first round: PEBBLE's unsupervised reward,
  the kNN distance of s' to the buffer's states, normalised by its running std, computed per
  batch (each stored transition holds 0 until then). RIME also warm-starts r_hat on it.
  S-EPOA does not update before its first round.
- After the first round: r_hat on every stored and every new transition (the buffer is
  relabelled at each round), plus RUNE's bonus beta_t times the ensemble's std of r_hat; or,
  in the true-reward diagnostic (`reward.true_reward`), the environment's reward.
"""

from __future__ import annotations

from typing import Any, TypeVar

import numpy as np
import torch

from runvocab.config import RunConfig
from runvocab.names import PEBBLE_FAMILY
from trainer.entropy import RunningMeanStd, knn_distance
from trainer.feedback import Feedback, PreferenceFeedback
from trainer.nets import NumpyMLP
from trainer.replay_buffer import ReplayBuffer
from trainer.reward_model import RewardModel
from trainer.rune import rune_beta
from trainer.true_reward_rounds import TrueRewardRounds

B = TypeVar("B", bound=Any)
"""a replay batch: SAC's, or one that also carries skills"""


class TrueReward:
    """The SAC oracle's reward: the environment's, stored and trained on as it is."""

    unsupervised_steps = 0
    learned = False
    """it never trains on r_hat"""

    def at_step(self, obs: np.ndarray, action: np.ndarray, true_reward: float) -> float:
        return true_reward

    def batch(self, batch: B, step: int) -> B:
        return batch

    def first_round_closed(self, step: int) -> None:
        """Never called: the oracle's rounds never open."""

    def episode_row(self, step: int) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Nothing to restore: the true reward has no state."""


class AgentReward:
    """The reward of a preference-learning run's agent, per step (what the buffer stores) and
    per batch (what an update trains on)."""

    def __init__(self, cfg: RunConfig, buffer: ReplayBuffer,
                 feedback: PreferenceFeedback | TrueRewardRounds, device: torch.device):
        self.cfg, self.buffer, self.feedback, self.device = cfg, buffer, feedback, device
        self.entropy_stats = RunningMeanStd()
        self.start_step: int | None = None
        """the step the first round closed at: RUNE's t counts from here"""
        self._host_reward: NumpyMLP | None = None
        """r_hat of one transition in NumPy, on every device: on a GPU its batch of one cost the
        host more in launches and copies (about 0.4 ms a step on an H200's host, benchmarks/
        README.md) than NumPy's arithmetic here (about 60 us for 3 x 256 x 3)"""
        self._host_reward_round = -1
        """the round `_host_reward` was made after: on a GPU it holds a copy of the parameters,
        which change only as a round closes"""

    @property
    def unsupervised_steps(self) -> int:
        """Steps on PEBBLE's unsupervised reward after the seed steps, before the first round."""
        return self.cfg.unsup_steps if self.cfg.algo in PEBBLE_FAMILY else 0

    @property
    def learned(self) -> bool:
        """After the first round: the agent trains on r_hat."""
        return self.feedback.rounds > 0

    def at_step(self, obs: np.ndarray, action: np.ndarray, true_reward: float) -> float:
        """The reward stored with a new transition: the ensemble's mean r_hat."""
        if not self.learned:
            return 0.0  # the unsupervised reward is computed per batch
        if isinstance(self.feedback, TrueRewardRounds):
            return true_reward
        if self._host_reward_round != self.feedback.rounds:
            # On the CPU, views of the parameters; on a GPU, a copy (one wait a round).
            self._host_reward = NumpyMLP(list(self.feedback.model.ensemble.layers),
                                         "leaky_relu", "tanh")
            self._host_reward_round = self.feedback.rounds
        assert self._host_reward is not None
        return float(self._host_reward(np.concatenate([obs, action])[None]).mean())

    @property
    def _model(self) -> RewardModel:
        """r_hat, which only a preference run's feedback has (RUNE's bonus, RIME's warm start)."""
        assert isinstance(self.feedback, PreferenceFeedback)
        return self.feedback.model

    def batch(self, batch: B, step: int) -> B:
        """`batch` carrying the reward the agent trains on at `step`."""
        if not self.learned:
            dist = self.entropy_distance(batch.next_obs)
            self.entropy_stats.update(dist)
            batch = batch._replace(reward=(dist / self.entropy_stats.std).unsqueeze(1))
            if self.cfg.reward.rime:
                self._warm_start_reward_model()
        elif self.cfg.reward.rune:
            bonus = self._model.reward_std(batch.obs, batch.action)
            batch = batch._replace(reward=batch.reward + self.rune_beta(step) * bonus.unsqueeze(1))
        return batch

    def first_round_closed(self, step: int) -> None:
        """The agent trains on r_hat from `step` on."""
        self.start_step = step

    def rune_beta(self, step: int) -> float:
        assert self.start_step is not None
        return rune_beta(self.cfg.reward, step - self.start_step)

    def episode_row(self, step: int) -> dict[str, float]:
        """What an episode's metrics row adds: RUNE's current beta once it applies."""
        if not self.cfg.reward.rune or self.start_step is None:
            return {}
        return {"rune_beta": self.rune_beta(step)}

    def entropy_distance(self, next_obs: torch.Tensor) -> torch.Tensor:
        points = self.buffer.next_obs[: len(self.buffer)]
        return knn_distance(next_obs, points, self.cfg.entropy_k + 1)

    def _warm_start_reward_model(self) -> None:
        """RIME: regress r_hat onto the state-entropy reward of fresh batches, standardised and
        scaled into tanh's range, so the first round starts from a reward the agent knows."""
        for _ in range(self.cfg.reward.rime_warm_start_updates):
            batch = self.buffer.sample(self.cfg.sac.batch_size)
            z = (self.entropy_distance(batch.next_obs) - self.entropy_stats.mean) / (
                self.entropy_stats.std)
            target = z / z.abs().max().clamp(min=1e-8)
            self._model.regress(torch.cat([batch.obs, batch.action], dim=1), target)

    def state_dict(self) -> dict[str, Any]:
        return {"reward_start_step": self.start_step,
                "entropy_stats": self.entropy_stats.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.start_step = state.get("reward_start_step")
        self.entropy_stats.load_state_dict(state["entropy_stats"])


def make_agent_reward(cfg: RunConfig, buffer: ReplayBuffer, feedback: Feedback,
                      device: torch.device) -> TrueReward | AgentReward:
    """The true reward for a run without preference feedback (the SAC oracle), else the
    learned one."""
    if isinstance(feedback, PreferenceFeedback | TrueRewardRounds):
        return AgentReward(cfg, buffer, feedback, device)
    return TrueReward()

"""Feedback rounds on the true reward: the agent side of a preference-learning run, alone.

A diagnostic (`reward.true_reward`): the run keeps its schedule, its rounds and their budget,
but a round asks nothing and trains no reward model. From the first round on the agent trains
on the environment's reward, and S-EPOA's R_theta is refitted on true returns (the pool's, or
every replay episode's), from which z_task is drawn as usual. Compared with the labelled run at
equal updates, it separates what the agent makes of a given reward from what the labels give
it (specs/small/sepoa-true-reward.toml).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from runvocab.config import FeedbackConfig
from trainer.replay_buffer import ReplayBuffer
from trainer.return_estimator import ReplayEpisodes, ReturnEstimator
from trainer.trajectories import TrajectoryPool, stacked_skills


class TrueRewardRounds:
    """Rounds at the labelled run's times that spend no answers: each round counts the
    queries the labelled run would ask against the budget, so both runs have as many."""

    labels_used = 0
    pending: list = []
    """never a query to answer"""

    def __init__(self, cfg: FeedbackConfig, estimator: ReturnEstimator | None,
                 replay: ReplayEpisodes | None = None):
        self.cfg, self.estimator, self.replay = cfg, estimator, replay
        self.rounds = 0
        self.queries_not_asked = 0
        """what the labelled run would have asked by now"""

    @property
    def budget_left(self) -> int:
        """As `PreferenceFeedback.budget_left`, with every round's queries counted as asked."""
        k = self.cfg.labels_per_query
        return max(0, self.cfg.budget - self.queries_not_asked * k) // k * k

    def finish_round(self, pool: TrajectoryPool, answers: dict, **_: Any) -> dict[str, float]:
        """Close a round at once: R_theta refitted on true returns where the run has one."""
        if answers:
            raise ValueError("a true-reward run asks nothing, so it takes no answers")
        n = min(self.cfg.per_round, self.budget_left // self.cfg.labels_per_query)
        self.queries_not_asked += n
        metrics: dict[str, float] = {"round": self.rounds, "queries": 0, "answered": 0,
                                     "answers": 0, "labels_used": 0}
        if self.estimator is not None:
            skills, returns = self.estimator_data(pool)
            metrics |= self.estimator.fit(skills, returns)
        self.rounds += 1
        return metrics

    def estimator_data(self, pool: TrajectoryPool) -> tuple[np.ndarray, np.ndarray]:
        """Skills and true returns R_theta is fitted on (its targets)."""
        if self.replay is not None:
            return self.replay.skills_and_returns(None)
        trajectories = list(pool.trajectories)
        return (stacked_skills(trajectories),
                np.array([t.true_return for t in trajectories], dtype=np.float64))

    @staticmethod
    def relabel(buffer: ReplayBuffer) -> None:
        """Every stored transition trains on its true reward from now on."""
        buffer.reward.copy_(buffer.true_reward)

    def summary(self) -> dict[str, int]:
        return {"labels_used": 0, "rounds": self.rounds}

    def state_dict(self) -> dict[str, Any]:
        return {"rounds": self.rounds, "queries_not_asked": self.queries_not_asked} | (
            {"estimator": self.estimator.state_dict()} if self.estimator else {})

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if not state:
            return
        self.rounds, self.queries_not_asked = state["rounds"], state["queries_not_asked"]
        if self.estimator is not None:
            self.estimator.load_state_dict(state["estimator"])

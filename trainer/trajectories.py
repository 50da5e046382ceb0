"""Finished trajectories: a FIFO of the last N episodes with everything a query needs.

Each `Trajectory` carries its own observations, actions, ground-truth rewards, the physics state
of every step (to re-render a segment exactly), its episode context and the skill that produced
it. Because the skill is a field of the trajectory, evicting old trajectories can never leave a
skill attached to the wrong one.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import cast

import numpy as np


@dataclass
class Trajectory:
    id: int
    """running episode number within the run"""
    obs: np.ndarray
    """(T, obs_dim) float32: the observation each action was taken in"""
    actions: np.ndarray
    """(T, action_dim) float32"""
    true_rewards: np.ndarray
    """(T,) float32 ground-truth rewards (teachers and evaluation only)"""
    states: np.ndarray
    """(T, state_dim) float64 physics state at each observation"""
    context: int
    """episode context the physics state needs (Metaworld's task variant)"""
    success: bool
    """Metaworld: success at any step of the episode"""
    skill: np.ndarray | None = None
    """the skill vector that generated the trajectory (skill-based methods)"""

    @property
    def length(self) -> int:
        return len(self.true_rewards)

    @property
    def true_return(self) -> float:
        return float(self.true_rewards.sum(dtype=np.float64))


class EpisodeRecorder:
    """Collects one episode into preallocated arrays, then hands it out as a `Trajectory`."""

    def __init__(self, obs_dim: int, action_dim: int, state_dim: int, max_length: int):
        self.obs = np.empty((max_length, obs_dim), np.float32)
        self.actions = np.empty((max_length, action_dim), np.float32)
        self.rewards = np.empty(max_length, np.float32)
        self.states = np.empty((max_length, state_dim), np.float64)
        self.t = 0
        self.success = False

    def record(self, obs: np.ndarray, action: np.ndarray, reward: float, state: np.ndarray,
               success: bool) -> None:
        t = self.t
        self.obs[t], self.actions[t], self.rewards[t], self.states[t] = obs, action, reward, state
        self.success |= success
        self.t = t + 1

    def finish(self, traj_id: int, context: int, skill: np.ndarray | None = None) -> Trajectory:
        t = self.t
        traj = Trajectory(
            id=traj_id,
            obs=self.obs[:t].copy(),
            actions=self.actions[:t].copy(),
            true_rewards=self.rewards[:t].copy(),
            states=self.states[:t].copy(),
            context=context,
            success=self.success,
            skill=None if skill is None else np.asarray(skill, np.float32).copy(),
        )
        self.t, self.success = 0, False
        return traj


class TrajectoryPool:
    """The last `capacity` finished trajectories, oldest first, and every finished return."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.trajectories: deque[Trajectory] = deque(maxlen=capacity)
        self.returns: list[float] = []
        """ground-truth return of every finished trajectory of the run, in order"""

    def __len__(self) -> int:
        return len(self.trajectories)

    def __getitem__(self, i: int) -> Trajectory:
        return self.trajectories[i]

    def add(self, traj: Trajectory) -> None:
        self.trajectories.append(traj)
        self.returns.append(traj.true_return)

    def state_dict(self) -> dict:
        return {"trajectories": list(self.trajectories), "returns": list(self.returns)}

    def load_state_dict(self, state: dict) -> None:
        self.trajectories = deque(
            (t if isinstance(t, Trajectory) else Trajectory(**t) for t in state["trajectories"]),
            maxlen=self.capacity,
        )
        self.returns = list(state["returns"])


def stacked_skills(trajectories: Iterable[Trajectory]) -> np.ndarray:
    """(N, skill_dim): the skills the trajectories were played with (S-EPOA's: each has one)."""
    return np.stack(cast(list[np.ndarray], [t.skill for t in trajectories]))

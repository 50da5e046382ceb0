"""Trajectories of random observations, actions and rewards, for the tests of feedback rounds
that need a pool but no environment."""

from __future__ import annotations

import numpy as np

from trainer.trajectories import Trajectory, TrajectoryPool


def random_pool(n: int, length: int, obs_dim: int, action_dim: int) -> TrajectoryPool:
    """`n` trajectories of `length` steps (ids 0..n-1), drawn from a fixed seed: the same pool
    at every call."""
    rng = np.random.default_rng(0)
    pool = TrajectoryPool(n)
    for i in range(n):
        pool.add(Trajectory(
            id=i, obs=rng.normal(size=(length, obs_dim)).astype(np.float32),
            actions=rng.uniform(-1, 1, (length, action_dim)).astype(np.float32),
            true_rewards=rng.uniform(0, 1, length).astype(np.float32),
            states=np.zeros((length, 4)), context=0, success=False))
    return pool

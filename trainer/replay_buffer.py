"""The replay buffer: a ring of transitions held as tensors on the training device.

Each transition keeps its ground-truth reward (for the oracle and for evaluation) beside the
reward the agent trains on, which the preference loop rewrites after every reward-model update.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from trainer.sac import Batch


class ReplayBuffer:
    def __init__(self, obs_dim: int, action_dim: int, capacity: int, device: torch.device, seed: int):
        self.capacity, self.device = capacity, device
        self.obs = torch.empty(capacity, obs_dim, device=device)
        self.next_obs = torch.empty(capacity, obs_dim, device=device)
        self.action = torch.empty(capacity, action_dim, device=device)
        self.true_reward = torch.empty(capacity, 1, device=device)
        self.reward = torch.empty(capacity, 1, device=device)
        self.size = 0
        self.cursor = 0
        self.generator = torch.Generator(device="cpu").manual_seed(seed)

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, true_reward: float,
            next_obs: np.ndarray) -> None:
        i = self.cursor
        self.obs[i] = torch.from_numpy(obs)
        self.action[i] = torch.from_numpy(action)
        self.next_obs[i] = torch.from_numpy(next_obs)
        self.reward[i, 0] = reward
        self.true_reward[i, 0] = true_reward
        self.cursor = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch_size: int) -> Batch:
        idx = torch.randint(0, self.size, (batch_size,), generator=self.generator).to(self.device)
        return Batch(self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx])

    @torch.no_grad()
    def relabel(self, reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                chunk: int = 65_536) -> None:
        """Rewrite every stored reward with `reward_fn(obs, action)` -> (n,)."""
        for start in range(0, self.size, chunk):
            end = min(start + chunk, self.size)
            self.reward[start:end, 0] = reward_fn(self.obs[start:end], self.action[start:end])

    def state_dict(self) -> dict:
        n = self.size
        return {
            "obs": self.obs[:n].cpu(),
            "next_obs": self.next_obs[:n].cpu(),
            "action": self.action[:n].cpu(),
            "reward": self.reward[:n].cpu(),
            "true_reward": self.true_reward[:n].cpu(),
            "size": n,
            "cursor": self.cursor,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        n = state["size"]
        for name in ("obs", "next_obs", "action", "reward", "true_reward"):
            getattr(self, name)[:n] = state[name].to(self.device)
        self.size, self.cursor = n, state["cursor"]
        self.generator.set_state(state["generator"])

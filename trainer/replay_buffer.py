"""The replay buffer: a ring of transitions held as tensors on the training device.

Each transition keeps its ground-truth reward (for the oracle and for evaluation) beside the
reward the agent trains on, which the preference loop rewrites after every reward-model update.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import numpy as np
import torch

from trainer.sac import Batch
from trainer.utils import copy_async


class ReplayBuffer:
    def __init__(self, obs_dim: int, action_dim: int, capacity: int, device: torch.device,
                 seed: int, skill_dim: int = 0):
        """`skill_dim`: a column block for each transition's skill (`SkillReplayBuffer`)."""
        self.capacity, self.device = capacity, device
        widths = [obs_dim, action_dim, obs_dim, 1, 1] + ([skill_dim] if skill_dim else [])
        # One row per transition, each field a block of its columns: on a GPU `add` writes a
        # transition in one copy instead of one per field.
        self._rows = torch.empty(capacity, sum(widths), device=device)
        self._fields: list[torch.Tensor] = list(self._rows.split(widths, dim=1))
        """what `add` writes, in the order of its values"""
        self.obs, self.action, self.next_obs, self.reward, self.true_reward = self._fields[:5]
        self.size = 0
        self.cursor = 0
        # Indices are drawn where the buffer lives: on a GPU, sampling costs no host round trip.
        self.generator = torch.Generator(device=device).manual_seed(seed)
        # On the CPU, `add` writes through NumPy views of the same memory: plain array writes
        # instead of torch indexing calls (~1.5 us instead of ~15-25 us a step).
        self._arrays = [f.numpy() for f in self._fields] if device.type == "cpu" else None

    def __len__(self) -> int:
        return self.size

    def add(self, obs: np.ndarray, action: np.ndarray, reward: float, true_reward: float,
            next_obs: np.ndarray, skill: np.ndarray | None = None) -> None:
        """Store one transition; `skill`, the episode's (`EpisodeMeta.skill`), is kept by
        `SkillReplayBuffer` only."""
        self._write([obs, action, next_obs, reward, true_reward])

    def _write(self, values: list) -> None:
        """`values`, one per field, into the row at the cursor."""
        i = self.cursor
        if self._arrays is not None:
            for array, value in zip(self._arrays, values, strict=True):
                array[i] = value
        else:
            self._write_on_device(i, values)
        self.cursor = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def _write_on_device(self, i: int, values: list) -> None:
        """The row in one asynchronous copy: with a plain copy per field a GPU run would wait
        for the GPU's queued work (the last update) once per field."""
        row = np.concatenate([np.asarray(value, np.float32).reshape(field.shape[1])
                              for field, value in zip(self._fields, values, strict=True)])
        copy_async(row, self._rows[i])

    def indices(self, batch_size: int) -> torch.Tensor:
        """`batch_size` uniform indices into the stored transitions, on the buffer's device."""
        return torch.randint(0, self.size, (batch_size,), generator=self.generator,
                             device=self.device)

    def sample(self, batch_size: int) -> Batch:
        idx = self.indices(batch_size)
        return Batch(self.obs[idx], self.action[idx], self.reward[idx], self.next_obs[idx])

    @torch.no_grad()
    def relabel(self, reward_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                chunk: int = 65_536) -> None:
        """Rewrite every stored reward with `reward_fn(obs, action)` -> (n,)."""
        for start in range(0, self.size, chunk):
            end = min(start + chunk, self.size)
            self.reward[start:end, 0] = reward_fn(self.obs[start:end], self.action[start:end])

    @torch.no_grad()
    def reward_correlation(self) -> float:
        """Pearson correlation of the stored (learned) reward with the true reward over the
        buffer: whether the reward model ranks transitions as the task does (nan when either
        is constant)."""
        both = torch.cat([self.reward[: self.size], self.true_reward[: self.size]], dim=1)
        if self.size < 2 or bool((both.std(dim=0) == 0).any()):
            return float("nan")
        return float(torch.corrcoef(both.T.double())[0, 1])

    def state_dict(self) -> dict:
        n = self.size
        # Copies, not views: torch.save writes a view's whole storage, i.e. the full capacity.
        return {
            "obs": self.obs[:n].to("cpu", copy=True),
            "next_obs": self.next_obs[:n].to("cpu", copy=True),
            "action": self.action[:n].to("cpu", copy=True),
            "reward": self.reward[:n].to("cpu", copy=True),
            "true_reward": self.true_reward[:n].to("cpu", copy=True),
            "size": n,
            "cursor": self.cursor,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        n = state["size"]
        for name in ("obs", "next_obs", "action", "reward", "true_reward"):
            getattr(self, name)[:n] = state[name].to(self.device)
        self.size, self.cursor = n, state["cursor"]
        saved = state["generator"]
        if len(saved) == len(self.generator.get_state()):
            self.generator.set_state(saved)
        else:  # saved on another kind of device: carry on with a stream seeded by that state
            self.generator.manual_seed(int.from_bytes(hashlib.sha256(
                saved.numpy().tobytes()).digest()[:8], "little"))

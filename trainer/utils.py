"""Small helpers that keep the training loop legible: step predicates, seeding, device choice."""

from __future__ import annotations

import random

import numpy as np
import torch


class Every:
    """True once every `period` steps (never when period <= 0)."""

    def __init__(self, period: int):
        self.period = period

    def __call__(self, step: int) -> bool:
        return self.period > 0 and step % self.period == 0


class Until:
    """True while step < limit."""

    def __init__(self, limit: int):
        self.limit = limit

    def __call__(self, step: int) -> bool:
        return step < self.limit


def set_seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for, but torch sees no CUDA device")
    if name.split(":")[0] not in ("cpu", "cuda"):
        raise ValueError(f"unknown device {name!r}; valid: auto, cpu, cuda")
    return torch.device(name)

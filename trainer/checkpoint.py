"""Checkpoints as plain state dicts: tensors, numbers, strings, lists and dicts only.

NumPy arrays are stored as tensors so a checkpoint loads with `torch.load(weights_only=True)`,
which never executes pickled code. Writes go to a temporary file and are renamed into place,
so a run killed while saving keeps its previous checkpoint.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
import torch

_NDARRAY = "__ndarray__"


def _to_plain(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {_NDARRAY: torch.from_numpy(np.ascontiguousarray(obj)).clone()}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: _to_plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_to_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _from_plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {_NDARRAY}:
            return obj[_NDARRAY].numpy()
        return {k: _from_plain(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_from_plain(v) for v in obj]
    return obj


def save_checkpoint(path: str, state: dict) -> None:
    tmp = path + ".tmp"
    torch.save(_to_plain(state), tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load_checkpoint(path: str) -> dict:
    return _from_plain(torch.load(path, map_location="cpu", weights_only=True))


def random_state(rng: np.random.Generator, device: torch.device) -> dict:
    """The process's random streams a run draws from: its NumPy generator, torch's CPU stream
    and, on a GPU, CUDA's (a checkpoint's `rng`, `torch_rng` and `cuda_rng`)."""
    state = {"rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state()}
    if device.type == "cuda":
        state["cuda_rng"] = torch.cuda.get_rng_state()
    return state


def restore_random_state(state: dict, rng: np.random.Generator, device: torch.device) -> None:
    """Puts back what `random_state` saved (CUDA's stream only where both ran on a GPU)."""
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    if "cuda_rng" in state and device.type == "cuda":
        torch.cuda.set_rng_state(state["cuda_rng"])

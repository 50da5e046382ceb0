"""Small helpers for the training loop: seeding, device choice and host-to-device copies."""

from __future__ import annotations

import random

import numpy as np
import torch

from runvocab.names import device_name_error


def set_seed(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def pick_device(name: str) -> torch.device:
    """The device `name` (auto | cpu | cuda | cuda:<index>) stands for on this host; ValueError
    for any other name, or for a CUDA device torch does not see here."""
    problem = device_name_error(name)
    if problem:
        raise ValueError(problem)
    kind, _, index = name.partition(":")
    if kind == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if kind == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} was asked for, but torch sees no CUDA device")
        count = torch.cuda.device_count()
        if index and int(index) >= count:
            raise ValueError(f"device {name!r}: torch sees {count} CUDA device(s) here, "
                             f"cuda:0 to cuda:{count - 1}")
    return torch.device(name)


def copy_async(array: np.ndarray, target: torch.Tensor) -> None:
    """`array` into `target` without waiting for the device. A plain copy from host memory to
    a GPU first waits for all the GPU's queued work (a host sync); from pinned memory it is
    queued like a kernel (torch's pinned-memory cache keeps the block until the copy is
    done), straight into `target`."""
    source = torch.from_numpy(array)
    if target.device.type != "cuda":
        target.copy_(source)
        return
    target.copy_(source.pin_memory(), non_blocking=True)

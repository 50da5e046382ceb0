"""A round's reward training, saved as it goes, so that a run killed inside a round goes on from
its last saved epoch instead of training the whole round again.

A late round of a small-preset S-EPOA run is 50 reward epochs of about a minute each on a busy
core, and the run's checkpoint is written only as the round opens and closes: a kill in between
used to throw all of those epochs away. The file beside the checkpoint holds the reward model,
its optimiser, its random streams and the epoch counters, at most once a minute, once more
when training ends, and at once when the run is told to go (`RoundLeft`).

The saved state is tied to what the round trains on (`round_key`): a resumed run whose round
has other labels, another trajectory pool or another configuration trains from the start, as it
must. An uninterrupted run and one resumed from this file end with the same model, bit for bit.
"""

from __future__ import annotations

import hashlib
import os
import time
from collections.abc import Iterable

import numpy as np

from trainer.checkpoint import load_checkpoint, save_checkpoint


class RoundLeft(Exception):
    """Told to go inside a round (a worker's SIGTERM or Slurm's warning): the round's reward
    training is saved up to epoch `epochs`, and the run's checkpoint stays the one written as
    the round opened, which a resumed run goes on from."""

    def __init__(self, epochs: int):
        super().__init__(f"left inside a round, its reward training saved at epoch {epochs}")
        self.epochs = epochs


ROUND_PROGRESS = "round-progress.pt"
SAVE_EVERY_SECONDS = 60.0
"""a minute of training at most is lost to a kill; a save takes milliseconds"""


def round_key(parts: Iterable[object]) -> str:
    """A digest of a round's inputs: arrays by their bytes, shapes and types, the rest by repr."""
    digest = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            digest.update(f"{part.dtype}{part.shape}".encode())
            digest.update(np.ascontiguousarray(part).tobytes())
        else:
            digest.update(repr(part).encode())
        digest.update(b"\0")
    return digest.hexdigest()


class RoundProgress:
    """The run's round-progress file (`path`), saved at most every `every_seconds`."""

    def __init__(self, path: str, every_seconds: float = SAVE_EVERY_SECONDS):
        self.path, self.every_seconds = path, every_seconds
        self._last_save = time.monotonic()

    def load(self, key: str) -> dict | None:
        """The state saved for the round `key`, or None (no file, or another round's)."""
        if not os.path.exists(self.path):
            return None
        state = load_checkpoint(self.path)
        return state["state"] if state.get("key") == key else None

    def due(self) -> bool:
        return time.monotonic() - self._last_save >= self.every_seconds

    def save(self, key: str, state: dict) -> None:
        save_checkpoint(self.path, {"key": key, "state": state})
        self._last_save = time.monotonic()

    def start(self) -> None:
        """A round's training begins: the first save comes `every_seconds` later."""
        self._last_save = time.monotonic()

    def clear(self) -> None:
        """The round is in the run's checkpoint: its progress is no longer needed."""
        if os.path.exists(self.path):
            os.remove(self.path)

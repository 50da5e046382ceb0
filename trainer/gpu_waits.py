"""Where the host waits for the GPU, for the CUDA test of a step's waits and for
benchmarks/profile_steps.py: torch's sync debug mode warns at each synchronising call (a
read-back, a copy from pageable memory), and each warning names the line of Python that made
it. Only torch's per-wait message counts: its one-time notice that the mode is a prototype also
speaks of "synchronizing operations" but is not a wait.
"""

from __future__ import annotations

import os
import warnings
from collections import Counter

import torch

WAIT_MESSAGE = "called a synchronizing CUDA operation"


def waits_in(caught: list[warnings.WarningMessage]) -> list[warnings.WarningMessage]:
    """The warnings among `caught` that are waits."""
    return [w for w in caught if WAIT_MESSAGE in str(w.message)]


class GpuWaits:
    """Records the waits between `start` and `stop` (or in a `with` block). Call
    `torch.cuda.synchronize()` before, so that earlier queued work is not counted."""

    def start(self) -> None:
        self._catcher = warnings.catch_warnings(record=True)
        self.caught = self._catcher.__enter__()
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")

    def stop(self) -> None:
        torch.cuda.set_sync_debug_mode("default")
        self._catcher.__exit__(None, None, None)

    def __enter__(self) -> GpuWaits:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def where(self) -> list[str]:
        """One entry a wait: the line that made it and torch's message."""
        return [f"{w.filename}:{w.lineno}: {w.message}" for w in waits_in(self.caught)]

    def by_line(self) -> Counter[str]:
        return Counter(f"{os.path.relpath(w.filename)}:{w.lineno}" for w in waits_in(self.caught))

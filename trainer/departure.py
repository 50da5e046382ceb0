"""A worker told to go: the signals that say so, and whether one came (`Departure`)."""

from __future__ import annotations

import signal
from typing import Any

LEAVE_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)
"""the signals that tell a worker to checkpoint, release its run and exit"""


class Departure:
    """Whether, and by which signal, this worker was told to go (`LEAVE_SIGNALS`)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.announced = False

    @property
    def due(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else "none"

    def on_signal(self, signum: int, _frame: Any) -> None:
        # Nothing printed here: the signal may have interrupted a print to the same stream.
        self.signum = signum
        for sig in LEAVE_SIGNALS:  # a second one ends the worker at once
            signal.signal(sig, signal.SIG_DFL)


def leave_on_signals(departure: Departure) -> dict[int, Any]:
    """Install `departure`'s handler for `LEAVE_SIGNALS`; the handlers it replaced (none
    outside the main thread, where signals cannot be handled)."""
    previous: dict[int, Any] = {}
    for sig in LEAVE_SIGNALS:
        try:
            previous[sig] = signal.signal(sig, departure.on_signal)
        except ValueError:  # not the main thread
            break
    return previous

"""Where a run's wall time goes: seconds per phase of the training loop, summed between rows.

Each episode row of episodes.csv carries the seconds every phase took since the row before
(`seconds_<phase>`), so summing a run's rows gives its whole profile, resumes included
(`benchmarks/run_profile.py` prints it). On a GPU the update launches its kernels without
waiting for them: their time shows up in whichever phase next waits on the device.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

PHASES = ("acting", "updates", "selection", "reward_training", "estimator", "waiting",
          "evaluation", "checkpoints")
"""acting: policy, environment and buffer; updates: SAC gradient updates (with their reward
relabelling); selection: choosing a round's queries; reward_training: training the reward
model on a round's labels and relabelling the buffer; estimator: S-EPOA's R_theta fit;
waiting: for a round's answers (people, or the queue); evaluation; checkpoints"""


class PhaseClock:
    def __init__(self) -> None:
        self.seconds = dict.fromkeys(PHASES, 0.0)
        self.since = time.perf_counter()

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[phase] += time.perf_counter() - start

    def add(self, phase: str, seconds: float) -> None:
        self.seconds[phase] += seconds

    def row(self) -> dict[str, float]:
        """`seconds_<phase>` since the last row, and `seconds_total` (the wall time since the
        last row: what no phase holds is the loop's own bookkeeping); then a fresh start."""
        now = time.perf_counter()
        row = {f"seconds_{phase}": round(s, 4) for phase, s in self.seconds.items()}
        row["seconds_total"] = round(now - self.since, 4)
        self.seconds, self.since = dict.fromkeys(PHASES, 0.0), now
        return row

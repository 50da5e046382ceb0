"""Named step predicates for the training loop (DrQ-v2's `Until` and `Every`, and a period
measured from the last time something happened, for work done at episode ends)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Until:
    """True while `step` is below `until`."""

    until: int

    def __call__(self, step: int) -> bool:
        return step < self.until


@dataclass(frozen=True)
class After:
    """True once `step` is past `after`."""

    after: int

    def __call__(self, step: int) -> bool:
        return step > self.after


@dataclass(frozen=True)
class Every:
    """True at every multiple of `every`; never when `every` is 0."""

    every: int

    def __call__(self, step: int) -> bool:
        return self.every > 0 and step % self.every == 0


@dataclass
class Period:
    """Due once `every` steps have passed since it last `happened` (never when `every` is 0).
    Checked at episode ends, so it fires at the first end past each period, not at multiples."""

    every: int
    last: int = 0

    def due(self, step: int) -> bool:
        return self.every > 0 and step - self.last >= self.every

    def happened(self, step: int) -> None:
        self.last = step

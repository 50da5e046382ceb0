"""Rate limits: a token bucket per key (an invite link, a labeller), in the server's memory.

A few lines of our own rather than a library's middleware: the label API's next is a plain
Starlette route (`server.routes.label`), and each limit is one dictionary look-up there. Each
server process keeps its own buckets, so N processes allow N times the rate; the limits guard
against one client hammering, not against a crowd (a real study's rate is far below them).
A refusal is a 429 with `Retry-After` in whole seconds (`TooFast`).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from fastapi import HTTPException

MAX_KEYS = 100_000
"""buckets kept at most; beyond that, full ones are forgotten (they allow a burst anyway)"""


class TooFast(HTTPException):
    """429 Too Many Requests, with the seconds to wait in `Retry-After`."""

    def __init__(self, what: str, wait_s: float):
        seconds = max(1, math.ceil(wait_s))
        super().__init__(429, f"{what}: too many requests; try again in {seconds} s",
                         headers={"Retry-After": str(seconds)})


@dataclass
class _Bucket:
    tokens: float
    at: float


class RateLimit:
    """`per_s` requests a second per key, in bursts of up to `burst`."""

    def __init__(self, per_s: float, burst: int):
        self.per_s, self.burst = per_s, burst
        self.clock = time.monotonic
        """seconds, for the buckets (a test may run them on a clock of its own)"""
        self._buckets: dict[object, _Bucket] = {}
        self._lock = threading.Lock()

    def wait_s(self, key: object, now: float | None = None) -> float:
        """Take one request for `key`: 0 when it may go ahead, else the seconds until it may."""
        now = self.clock() if now is None else now
        with self._lock:
            bucket = self._buckets.get(key)
            if bucket is None:
                if len(self._buckets) >= MAX_KEYS:
                    self._forget_full(now)
                bucket = self._buckets[key] = _Bucket(float(self.burst), now)
            bucket.tokens = min(self.burst, bucket.tokens + (now - bucket.at) * self.per_s)
            bucket.at = now
            if bucket.tokens >= 1:
                bucket.tokens -= 1
                return 0.0
            return (1 - bucket.tokens) / self.per_s

    def check(self, key: object, what: str) -> None:
        """TooFast (429) unless `key` may make a request now."""
        wait = self.wait_s(key)
        if wait > 0:
            raise TooFast(what, wait)

    def _forget_full(self, now: float) -> None:
        full = [key for key, b in self._buckets.items()
                if b.tokens + (now - b.at) * self.per_s >= self.burst]
        for key in full:
            del self._buckets[key]
        if len(self._buckets) >= MAX_KEYS:  # none full: start over rather than grow
            self._buckets.clear()

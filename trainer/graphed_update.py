"""An update step replayed from CUDA graphs (SAC's: `SAC.step`).

On a GPU the update is bound by kernel launches and host round trips, not by arithmetic: at
2 x 1024, batch 1024 it runs at the rate it runs at 2 x 256. A CUDA graph records the update's
kernels once and replays them with one launch. For that, the update reads its batch from
tensors that never move (each batch is copied into them), its optimisers keep their step
counts on the device (capturable Adam), and nothing in it reads a tensor on the host
(`SAC.step`). This module knows the update only as a step function of a batch and a schedule
slot, and the optimisers it steps. Each slot of the update schedule (with or without the actor
step, with or without the target step) has its own graph, recorded after a few eager warm-up
updates on a side stream, as CUDA graph capture asks. A critic reset or a loaded checkpoint
replaces optimiser state, so the graphs are dropped and recorded again.

Without capture (the CPU), the same static-batch path runs eagerly: what tests compare with
the plain update, so the graph's arithmetic is checked where there is no GPU.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from typing import Generic, TypeVar

import torch

Metrics = dict[str, torch.Tensor]
Slot = tuple[bool, bool]
B = TypeVar("B", bound=tuple[torch.Tensor, ...])
"""the batch: a tuple of tensors (SAC's `Batch`)"""

WARMUP_UPDATES = 3
"""eager updates per schedule slot before its graph is recorded (optimiser state and the
allocator's pools settle first)"""


class GraphedUpdate(Generic[B]):
    def __init__(self, step: Callable[[B, bool, bool], Metrics],
                 optimisers: Callable[[], Iterable[torch.optim.Optimizer]], capture: bool):
        self.step, self.optimisers, self.capture = step, optimisers, capture
        self.static: B | None = None
        """the batch every update reads, allocated at the first update's shapes"""
        self.graphs: dict[Slot, tuple[torch.cuda.CUDAGraph, Metrics]] = {}
        self.warm: Counter[Slot] = Counter()

    def forget(self) -> None:
        """Drop the recorded graphs (the optimisers' state tensors changed)."""
        self.graphs.clear()
        self.warm.clear()

    def __call__(self, batch: B, slot: Slot) -> Metrics:
        static = self._load(batch)
        if not self.capture:
            return self.step(static, *slot)
        recorded = self.graphs.get(slot)
        if recorded is not None:
            graph, metrics = recorded
            graph.replay()
            return metrics
        if self.warm[slot] < WARMUP_UPDATES:
            self.warm[slot] += 1
            return self._on_side_stream(static, slot)
        graph = torch.cuda.CUDAGraph()
        # Gradients set to None first: backward then allocates them from the graph's pool, and
        # every replay writes them in place.
        for opt in self.optimisers():
            opt.zero_grad(set_to_none=True)
        with torch.cuda.graph(graph):
            metrics = self.step(static, *slot)
        self.graphs[slot] = (graph, metrics)
        graph.replay()  # recording ran nothing: this is the update itself
        return metrics

    def _load(self, batch: B) -> B:
        if self.static is None or any(s.shape != b.shape for s, b in zip(self.static, batch,
                                                                           strict=True)):
            if self.static is not None:
                self.forget()  # graphs read the old tensors
            self.static = type(batch)(*(torch.empty_like(b) for b in batch))
        for target, source in zip(self.static, batch, strict=True):
            target.copy_(source)
        return self.static

    def _on_side_stream(self, static: B, slot: Slot) -> Metrics:
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            metrics = self.step(static, *slot)
        torch.cuda.current_stream().wait_stream(side)
        return metrics

"""SAC's update replayed from CUDA graphs.

On a GPU the update is bound by kernel launches and host round trips, not by arithmetic: at
2 x 1024, batch 1024 it runs at the rate it runs at 2 x 256. A CUDA graph records the update's
kernels once and replays them with one launch. For that, the update reads its batch from
tensors that never move (each batch is copied into them), its optimisers keep their step
counts on the device (capturable Adam), and nothing in it reads a tensor on the host
(`SAC.step`). Each slot of the update schedule (with or without the actor step, with or
without the target step) has its own graph, recorded after a few eager warm-up updates on a
side stream, as CUDA graph capture asks. A critic reset or a loaded checkpoint replaces
optimiser state, so the graphs are dropped and recorded again.

Without capture (the CPU), the same static-batch path runs eagerly: what tests compare with
the plain update, so the graph's arithmetic is checked where there is no GPU.
"""

from __future__ import annotations

from collections import Counter

import torch

from trainer.sac import SAC, Batch, UpdateMetrics

WARMUP_UPDATES = 3
"""eager updates per schedule slot before its graph is recorded (optimiser state and the
allocator's pools settle first)"""


class GraphedUpdate:
    def __init__(self, sac: SAC, capture: bool):
        self.sac, self.capture = sac, capture
        self.static: Batch | None = None
        """the batch every update reads, allocated at the first update's shapes"""
        self.graphs: dict[tuple[bool, bool], tuple[torch.cuda.CUDAGraph, UpdateMetrics]] = {}
        self.warm: Counter[tuple[bool, bool]] = Counter()

    def forget(self) -> None:
        """Drop the recorded graphs (the optimisers' state tensors changed)."""
        self.graphs.clear()
        self.warm.clear()

    def __call__(self, batch: Batch) -> UpdateMetrics:
        static = self._load(batch)
        slot = self.sac.schedule()
        if not self.capture:
            return self.sac.step(static, *slot)
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
        for opt in (self.sac.actor_opt, self.sac.critic_opt, self.sac.alpha_opt):
            opt.zero_grad(set_to_none=True)
        with torch.cuda.graph(graph):
            metrics = self.sac.step(static, *slot)
        self.graphs[slot] = (graph, metrics)
        graph.replay()  # recording ran nothing: this is the update itself
        return metrics

    def _load(self, batch: Batch) -> Batch:
        if self.static is None or any(s.shape != b.shape for s, b in zip(self.static, batch,
                                                                           strict=True)):
            if self.static is not None:
                self.forget()  # graphs read the old tensors
            self.static = Batch(*(torch.empty_like(b) for b in batch))
        for target, source in zip(self.static, batch, strict=True):
            target.copy_(source)
        return self.static

    def _on_side_stream(self, static: Batch, slot: tuple[bool, bool]) -> UpdateMetrics:
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            metrics = self.sac.step(static, *slot)
        torch.cuda.current_stream().wait_stream(side)
        return metrics

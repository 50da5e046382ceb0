"""kNN particle estimate of state entropy (PEBBLE's unsupervised pretraining reward) and the
running statistics that normalise it."""

from __future__ import annotations

import torch


def knn_distance(x: torch.Tensor, points: torch.Tensor, k: int, chunk: int = 8192) -> torch.Tensor:
    """Distance from each row of `x` (B, d) to its k-th nearest row of `points` (N, d).

    A row of `x` that is itself among `points` has itself as nearest neighbour at distance 0,
    so pass k + 1 to skip it (as PEBBLE does, comparing a batch with the whole buffer).
    """
    dists = torch.cat(
        [torch.cdist(x, points[i : i + chunk]) for i in range(0, len(points), chunk)], dim=1
    )
    return dists.kthvalue(k, dim=1).values


class RunningMeanStd:
    """Running mean and variance over batches (Chan et al.'s parallel update)."""

    def __init__(self, epsilon: float = 1e-4, var: float = 1.0):
        """`epsilon`: the prior's weight in counts; `var`: the prior variance."""
        self.mean, self.var, self.count = 0.0, var, epsilon

    def update(self, x: torch.Tensor) -> None:
        batch_mean, batch_var, n = x.mean().item(), x.var(unbiased=False).item(), x.numel()
        delta, total = batch_mean - self.mean, self.count + n
        self.mean += delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.var, self.count = m2 / total, total

    @property
    def std(self) -> float:
        return self.var**0.5

    def state_dict(self) -> dict:
        return {"mean": self.mean, "var": self.var, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = state["mean"], state["var"], state["count"]

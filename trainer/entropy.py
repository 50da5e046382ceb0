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
    """Running mean and variance over batches (Chan et al.'s parallel update).

    Once updated, mean and variance are float64 0-d tensors on the batches' device, so an
    update reads nothing back to the host: on a GPU, two reads a step had cost two syncs in
    PEBBLE's unsupervised phase and in every update of skill pretraining. The arithmetic is
    the same double-precision arithmetic, in the same order, as on Python floats."""

    def __init__(self, epsilon: float = 1e-4, var: float = 1.0):
        """`epsilon`: the prior's weight in counts; `var`: the prior variance."""
        self.mean: float | torch.Tensor = 0.0
        self.var: float | torch.Tensor = var
        self.count = epsilon

    def update(self, x: torch.Tensor) -> None:
        batch_mean, batch_var = x.mean().double(), x.var(unbiased=False).double()
        n = x.numel()
        delta, total = batch_mean - self.mean, self.count + n
        self.mean = self.mean + delta * n / total
        m2 = self.var * self.count + batch_var * n + delta**2 * self.count * n / total
        self.var, self.count = m2 / total, total

    @property
    def std(self) -> float | torch.Tensor:
        return self.var**0.5

    def state_dict(self) -> dict:
        # Floats, as ever: read back at checkpoints only.
        return {"mean": float(self.mean), "var": float(self.var), "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.mean, self.var, self.count = state["mean"], state["var"], state["count"]

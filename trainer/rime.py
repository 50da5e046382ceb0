"""RIME's robust label filter: the reward model trains only on labels it finds plausible.

Before each training epoch, each label y (the probability that the second segment is
preferred) is compared with the ensemble's mean prediction P by KL(y || P). With rho the
running maximum KL of the labels trusted so far and sigma their KL's standard deviation:

    trusted  when  KL < tau_lower = -ln(rho + delta) + alpha * rho + min(beta_t * sigma, tau_upper)
    flipped  when  KL > tau_upper   (the model confidently says the opposite: train on 1 - y)

and the rest sit this epoch out. beta_t = max(beta_min, beta_max - k * t), where t counts the
reward model's training epochs (passes over the labels) since the run began. Before any label
has been trusted, rho = 0 makes the bound -ln(delta), about 18: every label is trusted.

rho follows the largest trusted KL of each epoch as an exponential average (rate 0.1); sigma
is the standard deviation of all trusted KLs so far (a running, count-weighted variance).
"""

from __future__ import annotations

import math

import torch

from runvocab.config import RewardConfig
from trainer.entropy import RunningMeanStd

DELTA = 1e-8
"""keeps -ln(rho) finite before any label is trusted"""
MAX_RATE = 0.1
"""exponential-average rate of rho"""


def label_kl(target: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """KL(y || P) between Bernoulli labels y (0, 0.5 or 1) and predictions P, elementwise."""
    p = p.clamp(1e-7, 1 - 1e-7)

    def term(y: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        return torch.where(y > 0, y * torch.log(y.clamp(min=1e-12) / q), torch.zeros_like(y))

    return term(target, p) + term(1 - target, 1 - p)


def rime_beta(cfg: RewardConfig, epochs: int) -> float:
    """beta_t: from beta_max down to beta_min, linearly by k per epoch."""
    return max(cfg.rime_beta_min, cfg.rime_beta_max - cfg.rime_k * epochs)


def lower_bound(cfg: RewardConfig, rho: float, sigma: float, beta: float) -> float:
    """tau_lower = -ln(rho + delta) + alpha * rho + min(beta * sigma, tau_upper)."""
    return (-math.log(rho + DELTA) + cfg.rime_alpha * rho
            + min(beta * sigma, cfg.rime_tau_upper))


class RimeFilter:
    """Chooses each epoch's training labels and keeps the KL statistics between epochs."""

    def __init__(self, cfg: RewardConfig):
        self.cfg = cfg
        self.rho = 0.0
        self.kl = RunningMeanStd(epsilon=0.0, var=0.0)
        """the trusted KLs' running mean and variance (no prior)"""
        self.epochs = 0

    @property
    def sigma(self) -> float:
        return float(self.kl.std)  # once an epoch: the read-back costs nothing here

    def select(self, target: torch.Tensor,
               p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
        """Given every label's target and the model's mean P (n,), the indices to train on this
        epoch, their (possibly flipped) targets, and what was decided. Updates the statistics
        and counts the epoch."""
        kl = label_kl(target, p)
        tau_lower = lower_bound(self.cfg, self.rho, self.sigma, rime_beta(self.cfg, self.epochs))
        flipped = kl > self.cfg.rime_tau_upper
        trusted = (kl < tau_lower) & ~flipped
        self._update(kl[trusted])
        self.epochs += 1
        index = torch.nonzero(trusted | flipped).squeeze(1)
        targets = torch.where(flipped, 1 - target, target)[index]
        n = max(len(target), 1)
        info = {"rime_trusted_ratio": float(trusted.sum()) / n,
                "rime_flipped_ratio": float(flipped.sum()) / n, "rime_tau_lower": tau_lower}
        return index, targets, info

    def _update(self, kl: torch.Tensor) -> None:
        n = kl.numel()
        if n == 0:
            return
        self.rho += MAX_RATE * (float(kl.max()) - self.rho)
        self.kl.update(kl)

    def state_dict(self) -> dict:
        return {"rho": self.rho, "kl": self.kl.state_dict(), "epochs": self.epochs}

    def load_state_dict(self, state: dict) -> None:
        self.rho, self.epochs = state["rho"], state["epochs"]
        self.kl.load_state_dict(state["kl"])

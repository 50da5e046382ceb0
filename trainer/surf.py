"""SURF (Park et al. 2022): more out of each label for the preference reward model.

- Temporal cropping: every training batch takes one crop length L in [crop_min, crop_max] and
  cuts each segment of each pair at its own random offset to L steps (segments of 60 cropped to
  45-55 in the paper's table), so a label teaches about shifted and shortened views of its pair.
- Semi-supervised pseudo-labels: each batch also draws `unlabelled_ratio` times as many random
  unlabelled pairs from the trajectory pool; a member whose P[seg1 > seg0] on the uncropped
  pair is above `threshold` (or below 1 - threshold) labels the pair itself, and learns that
  label on the pair's crops (cropped as the labelled ones): the Bradley-Terry loss of the
  confident pairs, averaged over every drawn pair, is added with weight `weight`. Each member
  labels with its own prediction.

Usable with any selection rule (`reward.surf true`); S-EPOA's runs in the paper use it too.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

PairSampler = Callable[[int], tuple[np.ndarray, np.ndarray]]
"""n -> two (n, H, obs_dim + action_dim) float32 arrays of unlabelled segment pairs"""


def crop(segments: torch.Tensor, length: int, starts: torch.Tensor) -> torch.Tensor:
    """(B, H, D) segments cut to (B, length, D), each from its own start step."""
    steps = starts[:, None] + torch.arange(length, device=segments.device)[None]  # (B, L)
    return torch.gather(segments, 1, steps[..., None].expand(-1, -1, segments.shape[-1]))


def random_crops(seg0: torch.Tensor, seg1: torch.Tensor, length: int,
                 generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Both sides of each pair cut to `length` steps at independent random offsets."""
    b, h = seg0.shape[:2]
    if not 0 < length <= h:
        raise ValueError(f"crop length {length} does not fit segments of {h} steps")
    starts = torch.randint(0, h - length + 1, (2, b), generator=generator).to(seg0.device)
    return crop(seg0, length, starts[0]), crop(seg1, length, starts[1])


def pseudo_labels(p: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(target, confident) for predictions P[seg1 > seg0]: target 1 where p > threshold, 0
    where p < 1 - threshold; `confident` marks those, the only pairs trained on."""
    second, first = p > threshold, p < 1 - threshold
    return second.float(), second | first

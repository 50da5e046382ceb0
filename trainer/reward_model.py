"""The preference reward model: an ensemble of MLPs r_psi(s, a) with a tanh output, trained with
the Bradley-Terry cross-entropy on labelled segment pairs.

P[seg1 > seg0] = sigmoid(sum_t r(seg1_t) - sum_t r(seg0_t)). A label's target is the probability
that the second segment is preferred: 0 (first), 1 (second) or 0.5 (equal).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from runvocab.config import RewardConfig
from trainer.nets import EnsembleMLP
from trainer.reward_file import load_ensemble
from trainer.rime import RimeFilter
from trainer.surf import PairSampler, pseudo_labels, random_crops


def bradley_terry_loss(returns0: torch.Tensor, returns1: torch.Tensor,
                       target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of P[seg1 > seg0] = sigmoid(R1 - R0) against `target` (a probability).

    Shapes broadcast: (..., batch). Returns the mean over the last axis, keeping the rest.
    """
    logits = returns1 - returns0
    return F.binary_cross_entropy_with_logits(
        logits, target.expand_as(logits), reduction="none"
    ).mean(-1)


class LabelledPairs:
    """The labelled segment pairs the model trains on: (obs, action) of both segments, target."""

    def __init__(self) -> None:
        self.seg0: list[np.ndarray] = []
        self.seg1: list[np.ndarray] = []
        self.targets: list[float] = []

    def __len__(self) -> int:
        return len(self.targets)

    def add(self, seg0: np.ndarray, seg1: np.ndarray, target: float) -> None:
        """`seg0`, `seg1`: (H, obs_dim + action_dim) float32."""
        self.seg0.append(seg0)
        self.seg1.append(seg1)
        self.targets.append(target)

    def tensors(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return (
            torch.as_tensor(np.stack(self.seg0), device=device),
            torch.as_tensor(np.stack(self.seg1), device=device),
            torch.as_tensor(np.asarray(self.targets, np.float32), device=device),
        )

    def state_dict(self) -> dict:
        return {"seg0": self.seg0, "seg1": self.seg1, "targets": self.targets}

    def load_state_dict(self, state: dict) -> None:
        self.seg0, self.seg1, self.targets = state["seg0"], state["seg1"], list(state["targets"])


@dataclass
class TrainingProgress:
    """Where a round's reward training stands after an epoch: what a resumed training needs
    besides the model's own state to go on as if it had never stopped."""

    epochs: int = 0
    loss: float = float("nan")
    accuracy: float = 0.0
    confident: int = 0
    """SURF: the member-pairs pseudo-labelled with confidence so far"""
    pseudo: int = 0
    """SURF: the member-pairs drawn for pseudo-labels so far"""
    rime: dict[str, float] = field(default_factory=dict)
    finished: bool = False
    """training stopped early (accuracy reached, or RIME trusted no label) or ran all epochs"""


class RewardModel:
    def __init__(self, obs_dim: int, action_dim: int, cfg: RewardConfig, device: torch.device,
                 seed: int):
        self.cfg, self.device = cfg, device
        self.ensemble = EnsembleMLP(
            cfg.ensemble_size,
            obs_dim + action_dim,
            1,
            cfg.hidden_dim,
            cfg.hidden_layers,
            activation=nn.LeakyReLU,
            output_activation=nn.Tanh,
        ).to(device)
        if cfg.init_from:  # a model fitted offline (sepoa reward fit)
            load_ensemble(self.ensemble, cfg, cfg.init_from, obs_dim, action_dim)
        self.opt = torch.optim.Adam(self.ensemble.parameters(), lr=cfg.lr)
        self.generator = torch.Generator(device="cpu").manual_seed(seed)
        self.rime = RimeFilter(cfg) if cfg.rime else None

    @torch.no_grad()
    def member_rewards(self, obs_action: torch.Tensor, chunk: int = 65_536) -> torch.Tensor:
        """Per-member rewards of (n, obs_dim + action_dim) inputs: (ensemble, n)."""
        parts = [
            self.ensemble(obs_action[i : i + chunk])[..., 0]
            for i in range(0, len(obs_action), chunk)
        ]
        return torch.cat(parts, dim=1)

    @torch.no_grad()
    def reward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The reward the agent trains on: the ensemble mean, (n,)."""
        return self.member_rewards(torch.cat([obs, action], dim=-1)).mean(0)

    @torch.no_grad()
    def reward_std(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The ensemble's disagreement about each reward (RUNE's bonus): the members' std, (n,)."""
        return self.member_rewards(torch.cat([obs, action], dim=-1)).std(0, unbiased=False)

    def regress(self, obs_action: torch.Tensor, target: torch.Tensor) -> float:
        """One MSE step of every member towards `target` (n,) (RIME's warm start)."""
        e = self.cfg.ensemble_size
        pred = self.ensemble(obs_action.expand(e, -1, -1))[..., 0]
        loss = F.mse_loss(pred, target.expand(e, -1), reduction="none").mean(1).sum()
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return loss.item() / e

    @torch.no_grad()
    def _mean_p(self, seg0: torch.Tensor, seg1: torch.Tensor, chunk: int = 256) -> torch.Tensor:
        """The ensemble's mean P[seg1 preferred] for every labelled pair, (n,)."""
        e = self.cfg.ensemble_size
        parts = []
        for i in range(0, len(seg0), chunk):
            s0, s1 = (s[i : i + chunk].expand(e, -1, -1, -1) for s in (seg0, seg1))
            parts.append(torch.sigmoid(self._segment_returns(s1) - self._segment_returns(s0))
                         .mean(0))
        return torch.cat(parts)

    def _segment_returns(self, segments: torch.Tensor) -> torch.Tensor:
        """(E, B, H, D) member-specific segments -> (E, B) summed member rewards, summed in
        float32 (under bfloat16 autocast a sum of 50 rewards would keep 3 significant digits)."""
        e, b, h, d = segments.shape
        return self.ensemble(segments.reshape(e, b * h, d)).float().reshape(e, b, h).sum(-1)

    def train_round(self, pairs: LabelledPairs, unlabelled: PairSampler | None = None,
                    after_epoch: Callable[[TrainingProgress], None] | None = None,
                    resume: TrainingProgress | None = None) -> dict[str, float]:
        """Train on every label so far: up to `max_epochs` passes, each member on its own
        shuffle, stopping once the mean training accuracy reaches `stop_accuracy`. With
        `cfg.surf`, batches are temporally cropped and, given `unlabelled` pairs, pseudo-labelled
        pairs join the loss (trainer/surf.py). With `cfg.rime`, each epoch trains on the labels
        RIME's filter keeps, some flipped (trainer/rime.py).

        `after_epoch` hears where training stands after each epoch; `resume` goes on from such a
        point, the model's state (and `unlabelled`'s stream) having been put back as it was."""
        seg0, seg1, all_targets = pairs.tensors(self.device)
        e = self.cfg.ensemble_size
        p = resume or TrainingProgress()
        while p.epochs < self.cfg.max_epochs and not p.finished:
            p.epochs += 1
            active, target = torch.arange(len(all_targets), device=self.device), all_targets
            if self.rime is not None:
                active, kept, p.rime = self.rime.select(all_targets, self._mean_p(seg0, seg1))
                target = all_targets.clone()
                target[active] = kept
            n = len(active)
            if n == 0:
                p.finished = True
                break  # nothing trusted this epoch: keep the model as it is
            order = torch.stack([torch.randperm(n, generator=self.generator) for _ in range(e)])
            order = active[order.to(self.device)]
            correct = torch.zeros(e, device=self.device)
            counted = 0
            total_loss = 0.0
            for start in range(0, n, self.cfg.batch_size):
                idx = order[:, start : start + self.cfg.batch_size]  # (E, B)
                s0, s1, y = seg0[idx], seg1[idx], target[idx]
                length = None
                if self.cfg.surf:
                    length = int(torch.randint(self.cfg.surf_crop_min, self.cfg.surf_crop_max + 1,
                                               (), generator=self.generator))
                    s0, s1 = (c.reshape(e, -1, length, c.shape[-1]) for c in random_crops(
                        s0.flatten(0, 1), s1.flatten(0, 1), length, self.generator))
                # Autocast for this batch's forward passes only: autocast keeps its low-precision
                # copies of the weights until its block ends, so a block around several
                # optimiser steps would go on computing with the weights it first copied.
                with torch.autocast(self.device.type, torch.bfloat16, enabled=self.cfg.bf16):
                    r0, r1 = self._segment_returns(s0), self._segment_returns(s1)
                    loss = bradley_terry_loss(r0, r1, y).sum()
                    if length is not None and unlabelled is not None:
                        extra, confident = self._pseudo_label_loss(unlabelled, idx.shape[1],
                                                                   length)
                        loss = loss + self.cfg.surf_weight * extra
                        p.confident += confident
                        p.pseudo += e * idx.shape[1] * self.cfg.surf_unlabelled_ratio
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                self.opt.step()
                total_loss += loss.item() * idx.shape[1]
                # Accuracy over decisive labels only: an "equal" label has no right side.
                decisive = y != 0.5
                correct += (((r1 > r0) == (y > 0.5)) & decisive).sum(1).float()
                counted += int(decisive[0].sum())
            p.loss = total_loss / (n * e)
            p.accuracy = correct.sum().item() / (e * max(counted, 1))
            p.finished = p.accuracy >= self.cfg.stop_accuracy or p.epochs >= self.cfg.max_epochs
            if after_epoch is not None:  # a round is minutes of CPU: heartbeats, saves
                after_epoch(p)
        metrics = {"reward_loss": p.loss, "reward_accuracy": p.accuracy,
                   "reward_epochs": p.epochs} | p.rime
        if p.pseudo:
            metrics["surf_confident_ratio"] = p.confident / p.pseudo
        return metrics

    def _pseudo_label_loss(self, unlabelled: PairSampler, batch: int,
                           length: int) -> tuple[torch.Tensor, int]:
        """SURF's loss on self-labelled random pairs, and how many member-pairs were confident.

        As in SURF's paper and code: each member labels a pair from its uncropped segments,
        where its P[seg1 > seg0] is beyond the threshold, and learns that label on a random crop
        of the pair (another view: a loss on the view that gave the label would be below
        -ln(threshold), with next to no gradient). Each member's loss is the mean over every
        drawn pair, the unconfident counting 0; the members' losses are summed."""
        n = batch * self.cfg.surf_unlabelled_ratio
        if n == 0:
            return torch.zeros((), device=self.device), 0
        u0, u1 = (torch.as_tensor(u, device=self.device) for u in unlabelled(n))
        e = self.cfg.ensemble_size
        with torch.no_grad():
            p = torch.sigmoid(self._segment_returns(u1.expand(e, -1, -1, -1))
                              - self._segment_returns(u0.expand(e, -1, -1, -1)))
            y, keep = pseudo_labels(p, self.cfg.surf_threshold)
        c0, c1 = random_crops(u0, u1, length, self.generator)
        # Only confident pairs carry a gradient: forward just the pairs some member is confident
        # about, with autograd (most are not, and a pass over all of them would cost most of
        # SURF's training time).
        some = keep.any(0)
        kept = int(keep.sum())
        if not kept:
            return torch.zeros((), device=self.device), 0
        y, keep = y[:, some], keep[:, some]
        c0, c1 = c0[some].expand(e, -1, -1, -1), c1[some].expand(e, -1, -1, -1)
        logits = self._segment_returns(c1) - self._segment_returns(c0)
        losses = F.binary_cross_entropy_with_logits(logits, y, reduction="none") * keep
        return (losses.sum(-1) / n).sum(), kept

    def state_dict(self) -> dict:
        return {
            "ensemble": self.ensemble.state_dict(),
            "opt": self.opt.state_dict(),
            "generator": self.generator.get_state(),
        } | ({"rime": self.rime.state_dict()} if self.rime is not None else {})

    def load_state_dict(self, state: dict) -> None:
        self.ensemble.load_state_dict(state["ensemble"])
        self.opt.load_state_dict(state["opt"])
        self.generator.set_state(state["generator"])
        if self.rime is not None:
            self.rime.load_state_dict(state["rime"])

"""benchmarks/reward_floor.py counts a reward round's arithmetic as torch counts it."""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from runvocab.config import RewardConfig
from trainer.reward_model import LabelledPairs, RewardModel

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks"))
from reward_floor import reward_gflop, task_dims  # noqa: E402

TASK = "dmc:cheetah_run"
LENGTH = 10


def counted_round(cfg: RewardConfig, pairs: int) -> tuple[float, dict]:
    """(GFLOP torch counts, rounds.csv's row) of one round of `cfg` on random pairs."""
    obs, act = task_dims(TASK)
    rng = np.random.default_rng(0)
    labelled = LabelledPairs()
    for _ in range(pairs):
        labelled.add(*(rng.normal(size=(LENGTH, obs + act)).astype(np.float32)
                       for _ in range(2)), float(rng.integers(2)))

    def unlabelled(n: int) -> tuple[np.ndarray, np.ndarray]:
        return tuple(rng.normal(size=(n, LENGTH, obs + act)).astype(np.float32)
                     for _ in range(2))  # type: ignore[return-value]

    model = RewardModel(obs, act, cfg, torch.device("cpu"), seed=0)
    with FlopCounterMode(display=False) as counter:
        metrics = model.train_round(labelled, unlabelled if cfg.surf else None)
    return counter.get_total_flops() / 1e9, {"reward_epochs": metrics["reward_epochs"],
                                              "trained_pairs": pairs}


def run_config(cfg: RewardConfig) -> dict:
    return {"task": TASK, "reward": dataclasses.asdict(cfg),
            "feedback": {"segment_length": LENGTH}}


@pytest.mark.parametrize("epochs", [1, 3])
def test_the_floor_is_the_arithmetic_of_a_plain_round(epochs):
    cfg = RewardConfig(ensemble_size=2, hidden_dim=16, hidden_layers=3, batch_size=8,
                       max_epochs=epochs, stop_accuracy=1.01)
    counted, row = counted_round(cfg, pairs=20)
    assert row["reward_epochs"] == epochs
    assert reward_gflop(run_config(cfg), [row]) == pytest.approx(counted, rel=1e-9)


def test_the_floor_leaves_out_only_surfs_second_pass_over_confident_pairs():
    cfg = RewardConfig(ensemble_size=2, hidden_dim=16, hidden_layers=3, batch_size=8,
                       max_epochs=2, stop_accuracy=1.01, surf=True, surf_crop_min=6,
                       surf_crop_max=6, surf_unlabelled_ratio=2, surf_threshold=0.5)
    counted, row = counted_round(cfg, pairs=20)
    floor = reward_gflop(run_config(cfg), [row])
    labelled = reward_gflop(run_config(dataclasses.replace(cfg, surf_unlabelled_ratio=0)), [row])
    # At threshold 0.5 every unlabelled pair is confident, so the second pass forwards and
    # backwards them all: as much arithmetic per pair as a labelled pair's.
    assert floor < counted
    assert counted == pytest.approx(floor + cfg.surf_unlabelled_ratio * labelled, rel=1e-9)

"""SURF: temporal crops, the pseudo-label threshold, and a run with both switched on."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import torch

from runvocab.config import RewardConfig, build_config
from trainer.loop import TrainingRun
from trainer.reward_model import LabelledPairs, RewardModel
from trainer.surf import crop, pseudo_labels, random_crops


def test_a_crop_keeps_consecutive_steps_from_its_own_start():
    segments = torch.arange(2 * 60 * 1, dtype=torch.float32).reshape(2, 60, 1)
    out = crop(segments, 45, torch.tensor([0, 15]))
    assert out.shape == (2, 45, 1)
    assert out[0, :, 0].tolist() == list(range(0, 45))
    assert out[1, :, 0].tolist() == list(range(60 + 15, 60 + 60))


def test_random_crops_stay_inside_the_segments_and_move_each_side_independently():
    steps = torch.arange(60, dtype=torch.float32)[None, :, None].expand(500, 60, 1)
    g = torch.Generator().manual_seed(0)
    c0, c1 = random_crops(steps, steps, 45, g)
    first0, first1 = c0[:, 0, 0], c1[:, 0, 0]
    assert first0.min() == 0 and first0.max() == 15  # every offset 0..15 is reachable
    assert (first0 != first1).any()  # the two sides of a pair are cut at their own offsets
    assert torch.equal(c0[:, -1, 0], first0 + 44)
    with pytest.raises(ValueError, match="does not fit"):
        random_crops(steps, steps, 61, g)


def test_pseudo_labels_only_for_predictions_beyond_the_threshold():
    p = torch.tensor([0.9995, 0.999, 0.5, 0.001, 0.0004])
    target, confident = pseudo_labels(p, 0.999)
    assert confident.tolist() == [True, False, False, False, True]  # strict at the bounds
    assert target[confident].tolist() == [1.0, 0.0]


def test_pseudo_labelled_pairs_join_the_loss_only_when_confident():
    torch.manual_seed(0)
    cfg = RewardConfig(hidden_dim=16, hidden_layers=1, max_epochs=1, surf=True,
                       surf_crop_min=8, surf_crop_max=8, surf_threshold=0.6)
    model = RewardModel(3, 1, cfg, torch.device("cpu"), seed=0)
    pairs = LabelledPairs()
    rng = np.random.default_rng(0)
    for _ in range(8):
        pairs.add(rng.normal(size=(10, 4)).astype(np.float32),
                  rng.normal(size=(10, 4)).astype(np.float32), 1.0)

    def sampler(n):  # pairs whose second side is far larger: the model is sure of them
        first = np.zeros((n, 10, 4), np.float32)
        return first, first + 50.0

    metrics = model.train_round(pairs, sampler)
    assert 0 < metrics["surf_confident_ratio"] <= 1


def test_the_pseudo_label_loss_is_surfs_labels_from_whole_segments_learnt_on_crops():
    """Labels from each member's P on the uncropped pair, the loss on a crop of it, averaged
    over every drawn pair (SURF's code); only confident pairs are forwarded with autograd, and
    the loss and its gradient must equal that masked loss over all pairs."""
    torch.manual_seed(0)
    cfg = RewardConfig(hidden_dim=16, hidden_layers=2, surf=True, surf_threshold=0.55,
                       surf_unlabelled_ratio=4)
    model = RewardModel(3, 1, cfg, torch.device("cpu"), seed=0)
    rng = np.random.default_rng(0)
    u0, u1 = (rng.normal(size=(40, 10, 4)).astype(np.float32) * 3 for _ in range(2))
    state = model.generator.get_state()
    loss, kept = model._pseudo_label_loss(lambda n: (u0[:n], u1[:n]), 10, 8)
    assert 0 < kept < 3 * 40  # some member-pairs confident, not all
    loss.backward()
    grads = [p.grad.clone() for p in model.ensemble.parameters()]

    model.ensemble.zero_grad()
    model.generator.set_state(state)
    e = cfg.ensemble_size
    whole0, whole1 = (torch.as_tensor(u).expand(e, -1, -1, -1) for u in (u0, u1))
    p = torch.sigmoid(model._segment_returns(whole1) - model._segment_returns(whole0)).detach()
    y, keep = pseudo_labels(p, cfg.surf_threshold)
    c0, c1 = random_crops(torch.as_tensor(u0), torch.as_tensor(u1), 8, model.generator)
    logits = (model._segment_returns(c1.expand(e, -1, -1, -1))
              - model._segment_returns(c0.expand(e, -1, -1, -1)))
    losses = torch.nn.functional.binary_cross_entropy_with_logits(
        logits, y, reduction="none") * keep
    reference = losses.mean(-1).sum()
    reference.backward()
    assert int(keep.sum()) == kept
    torch.testing.assert_close(loss, reference)
    for got, want in zip(grads, (p.grad for p in model.ensemble.parameters()), strict=True):
        torch.testing.assert_close(got, want)


class FirstFeature(torch.nn.Module):
    """A reward ensemble whose every member's reward is the step's first feature."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.scale * x[..., :1]


def test_a_pair_sure_as_a_whole_teaches_on_crops_that_are_not():
    """The second side earns 10 at its first and last step: sure as a whole (P ~ 1), while a
    crop of 8 of its 10 steps that starts at step 1 holds neither. On such crops the pseudo-label
    still teaches (loss ln 2), far above what a crop's own confident label could (-ln 0.999)."""
    cfg = RewardConfig(surf=True, surf_threshold=0.999, surf_unlabelled_ratio=4)
    model = RewardModel(3, 1, cfg, torch.device("cpu"), seed=0)
    model.ensemble = FirstFeature()
    first = np.zeros((40, 10, 4), np.float32)
    second = first.copy()
    second[:, [0, 9], 0] = 10.0
    loss, kept = model._pseudo_label_loss(lambda n: (first[:n], second[:n]), 10, 8)
    e = cfg.ensemble_size
    assert kept == e * 40  # every member sure of every pair
    # Crops of the second side that start at step 1 (each with a loss of ln 2): 18 of the 40
    # here, 1 in 3 expected.
    assert 0.1 < loss.item() / e < 0.5


def test_a_pebble_run_with_surf_trains_on_crops_and_pseudo_labels(tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "steps": 1000, "threads": 1, "reward.surf": True,
        "reward.surf_crop_min": 15, "reward.surf_crop_max": 18, "reward.surf_threshold": 0.6,
        "run_dir": str(tmp_path / "run")})
    TrainingRun(cfg, progress=False).train()
    with open(tmp_path / "run" / "rounds.csv", newline="") as f:
        rounds = list(csv.DictReader(f))
    assert [int(r["labels_used"]) for r in rounds] == [10, 20]
    assert all(0 <= float(r["surf_confident_ratio"]) <= 1 for r in rounds)

import math

import numpy as np
import pytest
import torch

from runvocab.config import RewardConfig
from trainer.reward_model import LabelledPairs, RewardModel, bradley_terry_loss


def test_bradley_terry_loss_matches_hand_computation():
    # Segment returns R0 = 1.0, R1 = 3.0: P[seg1 > seg0] = e^3 / (e^1 + e^3).
    r0, r1 = torch.tensor([1.0]), torch.tensor([3.0])
    p1 = math.exp(3) / (math.exp(1) + math.exp(3))
    assert math.isclose(bradley_terry_loss(r0, r1, torch.tensor([1.0])).item(), -math.log(p1),
                        rel_tol=1e-6)
    assert math.isclose(bradley_terry_loss(r0, r1, torch.tensor([0.0])).item(),
                        -math.log(1 - p1), rel_tol=1e-6)
    # "equal" is a 0.5 target: the mean of both cross-entropies.
    equal = -(0.5 * math.log(p1) + 0.5 * math.log(1 - p1))
    assert math.isclose(bradley_terry_loss(r0, r1, torch.tensor([0.5])).item(), equal,
                        rel_tol=1e-6)


def test_bradley_terry_loss_averages_over_the_batch_per_member():
    r0 = torch.tensor([[0.0, 0.0], [1.0, 1.0]])  # (members, batch)
    r1 = torch.tensor([[0.0, 2.0], [1.0, 1.0]])
    y = torch.tensor([1.0, 1.0])
    loss = bradley_terry_loss(r0, r1, y)
    expected0 = (math.log(2) + math.log(1 + math.exp(-2))) / 2
    assert loss.shape == (2,)
    assert math.isclose(loss[0].item(), expected0, rel_tol=1e-6)
    assert math.isclose(loss[1].item(), math.log(2), rel_tol=1e-6)


@pytest.mark.parametrize("bf16", [False, True])
def test_reward_model_learns_a_planted_preference(bf16: bool):
    # The true reward is the first observation coordinate; labels follow segment sums. In
    # bfloat16 as well: each batch's forward passes under their own autocast (one around the
    # whole round would keep computing with the first weights, and the accuracy stays at 0.5).
    rng = np.random.default_rng(0)
    cfg = RewardConfig(hidden_dim=32, hidden_layers=2, max_epochs=200, stop_accuracy=0.99,
                       bf16=bf16)
    model = RewardModel(3, 1, cfg, torch.device("cpu"), seed=0)
    pairs = LabelledPairs()
    for _ in range(200):
        s0, s1 = rng.normal(size=(10, 4)).astype(np.float32), rng.normal(size=(10, 4)).astype(
            np.float32)
        pairs.add(s0, s1, 1.0 if s1[:, 0].sum() > s0[:, 0].sum() else 0.0)
    metrics = model.train_round(pairs)
    assert metrics["reward_accuracy"] >= 0.9
    # Held-out pairs are ranked by the planted reward.
    correct = 0
    for _ in range(100):
        s0, s1 = rng.normal(size=(10, 4)).astype(np.float32), rng.normal(size=(10, 4)).astype(
            np.float32)
        r0 = model.reward(torch.from_numpy(s0[:, :3]), torch.from_numpy(s0[:, 3:])).sum()
        r1 = model.reward(torch.from_numpy(s1[:, :3]), torch.from_numpy(s1[:, 3:])).sum()
        correct += bool((r1 > r0) == (s1[:, 0].sum() > s0[:, 0].sum()))
    assert correct >= 85


def test_training_stops_early_at_the_accuracy_threshold():
    pairs = LabelledPairs()
    for i in range(20):
        s = np.full((5, 3), i / 20, np.float32)
        pairs.add(s, s + 0.5, 1.0)

    def train(stop_accuracy: float) -> dict:
        torch.manual_seed(0)
        cfg = RewardConfig(hidden_dim=16, hidden_layers=1, max_epochs=60,
                           stop_accuracy=stop_accuracy)
        return RewardModel(2, 1, cfg, torch.device("cpu"), seed=0).train_round(pairs)

    reached = train(0.95)
    assert reached["reward_accuracy"] >= 0.95 and reached["reward_epochs"] < 60
    unreachable = train(1.01)
    assert unreachable["reward_epochs"] == 60

"""RIME: KL of a label against hand values, the bound and its beta schedule, the flip rule, the
filter on corrupted labels, and the warm start."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from runvocab.config import RewardConfig, build_config
from trainer.loop import TrainingRun
from trainer.reward_model import LabelledPairs, RewardModel
from trainer.rime import RimeFilter, label_kl, lower_bound, rime_beta


def test_label_kl_against_hand_values():
    y = torch.tensor([1.0, 0.0, 0.5, 1.0])
    p = torch.tensor([0.8, 0.8, 0.8, 0.5])
    expected = [math.log(1 / 0.8), math.log(1 / 0.2),
                0.5 * math.log(0.5 / 0.8) + 0.5 * math.log(0.5 / 0.2), math.log(2)]
    assert label_kl(y, p).tolist() == pytest.approx(expected, rel=1e-5)


def test_beta_falls_linearly_by_k_per_epoch_to_its_floor():
    dmc = build_config("dmc:cheetah_run", "paper", {"algo": "rime"}).reward
    assert dmc.rime_k == pytest.approx(1 / 30)
    assert [rime_beta(dmc, t) for t in (0, 15, 30, 60, 90)] == pytest.approx([3, 2.5, 2, 1, 1])
    mw = build_config("metaworld:door-open", "paper", {"algo": "rime"}).reward
    assert mw.rime_k == pytest.approx(1 / 300)
    assert rime_beta(mw, 300) == pytest.approx(2.0)


def test_lower_bound_against_hand_values_and_the_cap():
    cfg = RewardConfig(rime=True)  # alpha 0.5, tau_upper 3 ln 10
    assert cfg.rime_tau_upper == pytest.approx(3 * math.log(10))
    assert lower_bound(cfg, 0.5, 0.2, 3.0) == pytest.approx(-math.log(0.5) + 0.25 + 0.6)
    # The spread term is capped at tau_upper.
    assert lower_bound(cfg, 0.5, 10.0, 3.0) == pytest.approx(
        -math.log(0.5) + 0.25 + 3 * math.log(10))
    # Nothing trusted yet (rho = 0): about 18.4, so every label is trusted.
    assert lower_bound(cfg, 0.0, 0.0, 3.0) == pytest.approx(-math.log(1e-8))


def test_trusts_below_the_bound_flips_above_tau_upper_and_drops_the_rest():
    cfg = RewardConfig(rime=True)
    rime = RimeFilter(cfg)
    rime.rho, rime.kl.mean, rime.kl.var, rime.kl.count = 0.5, 0.3, 0.04, 10  # sigma 0.2
    bound = -math.log(0.5) + 0.25 + 3 * 0.2  # 1.543
    # KLs: 0.105 (trusted), 1.609 (above the bound: dropped), 9.21 (beyond 3 ln 10: flipped)
    y = torch.tensor([1.0, 1.0, 0.0, 0.5])
    p = torch.tensor([0.9, 0.2, 0.9999, 0.5])
    index, targets, info = rime.select(y, p)
    assert index.tolist() == [0, 2, 3]
    assert targets.tolist() == [1.0, 1.0, 0.5]  # the contradicted 0 becomes 1
    assert info["rime_tau_lower"] == pytest.approx(bound)
    assert info["rime_trusted_ratio"] == 0.5 and info["rime_flipped_ratio"] == 0.25
    # Statistics of the trusted KLs (0.1054 and 0): rho moves a tenth of the way to their max.
    assert rime.rho == pytest.approx(0.5 + 0.1 * (math.log(1 / 0.9) - 0.5), rel=1e-5)
    assert rime.kl.count == 12 and rime.epochs == 1


def _planted_pairs(n: int, corrupt: int, seed: int) -> tuple[LabelledPairs, np.ndarray]:
    """Pairs of random segments labelled by a planted reward (the first feature); the first
    `corrupt` labels are flipped."""
    rng = np.random.default_rng(seed)
    pairs, wrong = LabelledPairs(), np.zeros(n, bool)
    for i in range(n):
        s0, s1 = (rng.normal(size=(10, 4)).astype(np.float32) for _ in range(2))
        target = float(s1[:, 0].sum() > s0[:, 0].sum())
        if i < corrupt:
            target, wrong[i] = 1 - target, True
        pairs.add(s0, s1, target)
    return pairs, wrong


def test_the_filter_sets_aside_mostly_the_corrupted_labels():
    torch.manual_seed(0)
    cfg = RewardConfig(hidden_dim=32, hidden_layers=2, max_epochs=40, stop_accuracy=1.01,
                       rime=True)
    pairs, wrong = _planted_pairs(300, 45, seed=0)
    model = RewardModel(3, 1, cfg, torch.device("cpu"), seed=0)
    metrics = model.train_round(pairs)
    assert model.rime.epochs == 40
    seg0, seg1, y = pairs.tensors(torch.device("cpu"))
    kl = label_kl(y, model._mean_p(seg0, seg1))
    tau = lower_bound(cfg, model.rime.rho, model.rime.sigma, rime_beta(cfg, model.rime.epochs))
    set_aside = (kl >= tau).numpy()
    # Most corrupted labels are set aside (dropped or flipped) and few clean ones are.
    assert set_aside[wrong].mean() > 0.7
    assert set_aside[~wrong].mean() < 0.1
    assert 0.7 < metrics["rime_trusted_ratio"] < 0.95


def test_warm_start_fits_the_intrinsic_reward_and_keeps_the_critic(tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "rime", "steps": 410, "run_dir": str(tmp_path / "run"), "threads": 1})
    assert cfg.reward.rime and cfg.unsup_steps == 200  # the tiny preset's, not the paper's 2000
    run = TrainingRun(cfg, progress=False)
    fresh = RewardModel(run.env.obs_dim, run.env.action_dim, cfg.reward, run.device, seed=1)
    resets = []
    run.agent.reset_critic = lambda: resets.append(run.step)
    start_round = run.feedback.open_round
    fitted = {}

    def open_round(pool, step):
        # Just before the first round: how well does r_hat follow the entropy reward?
        batch = run.buffer.sample(256)
        dist = run.reward.entropy_distance(batch.next_obs)
        x = torch.cat([batch.obs, batch.action], 1)
        for name, model in (("warm", run.feedback.model), ("fresh", fresh)):
            r = model.member_rewards(x).mean(0)
            fitted[name] = float(np.corrcoef(r.numpy(), dist.numpy())[0, 1])
        return start_round(pool, step)

    run.feedback.open_round = open_round
    run.train()
    assert fitted["warm"] > 0.5 > abs(fitted["fresh"])
    assert resets == []  # RIME keeps the critic after the first round; PEBBLE resets it


def test_rime_runs_and_resumes_with_its_filter_state(tmp_path):
    overrides = {"algo": "rime", "steps": 1000, "run_dir": str(tmp_path / "run"), "threads": 1}
    run = TrainingRun(build_config("dmc:cheetah_run", "tiny", overrides), progress=False)
    run.train()
    state = run.feedback.model.rime.state_dict()
    assert state["epochs"] >= run.feedback.rounds >= 2 and state["kl"]["count"] > 0
    again = TrainingRun(build_config("dmc:cheetah_run", "tiny", overrides), resume=True,
                        progress=False)
    assert again.feedback.model.rime.state_dict() == state

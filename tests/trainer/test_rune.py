"""RUNE: the beta schedule against hand values, and the bonus the agent actually trains on."""

from __future__ import annotations

import math

import pytest
import torch

from runvocab.config import RewardConfig, build_config
from trainer.loop import TrainingRun
from trainer.rune import rune_beta


def test_beta_decays_per_environment_step_from_beta0():
    cfg = RewardConfig(rune=True)  # beta_0 0.05, rho 0.001: the paper's table
    assert rune_beta(cfg, 0) == 0.05
    assert rune_beta(cfg, 1) == pytest.approx(0.05 * 0.999)
    assert rune_beta(cfg, 1000) == pytest.approx(0.05 * math.exp(1000 * math.log(0.999)))
    assert rune_beta(cfg, 1000) == pytest.approx(0.018384, abs=1e-6)
    assert rune_beta(cfg, 5000) < 0.0004
    assert rune_beta(RewardConfig(rune_beta0=0.1, rune_decay=0.0), 10**6) == 0.1


def test_the_agent_trains_on_r_hat_plus_beta_t_times_the_ensemble_std(tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "rune", "steps": 700, "run_dir": str(tmp_path / "run"), "threads": 1,
        "reward.rune_beta0": 2.0, "reward.rune_decay": 0.01})
    assert cfg.reward.rune and not cfg.reward.surf
    run = TrainingRun(cfg, progress=False)
    seen = []
    update = run.agent.update

    def spy(batch):
        if run.reward.learned:
            seen.append((run.step, batch))
        return update(batch)

    run.agent.update = spy
    run.train()
    assert run.reward.start_step == cfg.seed_steps + cfg.unsup_steps  # the first round's step
    # One round only, so the buffer's r_hat and the model at the end are the ones each
    # update saw.
    assert run.feedback.rounds == 1 and len(seen) > 100
    model = run.feedback.model
    for step, batch in seen[:3] + seen[-3:]:
        beta = 2.0 * 0.99 ** (step - run.reward.start_step)
        members = model.member_rewards(torch.cat([batch.obs, batch.action], 1))
        r_hat, std = members.mean(0), members.std(0, unbiased=False)
        assert (std > 0).all()
        assert torch.allclose(batch.reward[:, 0], r_hat + beta * std, atol=1e-5)
    first_beta = 2.0 * 0.99 ** (seen[0][0] - run.reward.start_step)
    assert first_beta > 1.9  # t starts at the first round, not at the run's first step

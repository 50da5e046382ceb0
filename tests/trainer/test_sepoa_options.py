"""S-EPOA's options for running it as its authors' code does, and the true-reward diagnostic:
free initial rollouts, R_theta on every replay episode, the fixed-sigma actor, and rounds on the
true reward that keep the labelled run's updates."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest
import torch
from sepoa_docs import authors_overrides

from runvocab.config import SACConfig, build_config
from runvocab.first_round import first_round_step
from runvocab.names import ConfigError
from runvocab.validate import validate
from trainer.loop import TrainingRun
from trainer.return_estimator import ReplayEpisodes, ReturnEstimator
from trainer.sac import SAC, Batch, FixedStdActor, truncated
from trainer.skills.agent import SkillReplayBuffer
from trainer.true_reward_rounds import TrueRewardRounds

FAST = {"update_every": 4, "skill.estimator_hidden_dim": 32, "skill.estimator_steps": 50}


def _tiny(tmp_path, name: str, **overrides):
    base = {"algo": "sepoa", "steps": 1200, "threads": 1, "teacher.eps": 0.3,
            "skill.pretrain_steps": 0, "skill.snapshot_dir": str(tmp_path / "snapshots"),
            "run_dir": str(tmp_path / name)} | FAST
    return build_config("dmc:cheetah_run", "tiny", base | overrides)


def _rows(run_dir: str, stream: str) -> list[dict]:
    with open(os.path.join(run_dir, f"{stream}.csv"), newline="") as f:
        return list(csv.DictReader(f))


def test_on_the_true_reward_the_agent_makes_the_labelled_runs_updates_and_r_theta_fits_true_returns(
        tmp_path, monkeypatch):
    labelled = _tiny(tmp_path, "labelled")
    TrainingRun(labelled, progress=False).train()

    fits = []
    fit = ReturnEstimator.fit

    def record(self, skills, returns):
        pooled = list(run.pool.trajectories)  # what the pool holds as R_theta is fitted
        fits.append((skills.copy(), np.asarray(returns, dtype=np.float64).copy(),
                     np.stack([t.skill for t in pooled]),
                     [t.true_rewards.sum(dtype=np.float64) for t in pooled]))
        return fit(self, skills, returns)

    monkeypatch.setattr(ReturnEstimator, "fit", record)
    true = _tiny(tmp_path, "true", **{"reward.true_reward": True})
    run = TrainingRun(true, progress=False)
    run.train()

    by_step = {int(r["step"]): (r["updates"], r["reward_updates"])
               for r in _rows(labelled.run_dir, "episodes")}
    assert by_step == {int(r["step"]): (r["updates"], r["reward_updates"])
                       for r in _rows(true.run_dir, "episodes")}
    assert int(_rows(true.run_dir, "episodes")[-1]["updates"]) > 0
    # As many rounds, at the same steps; nothing asked, nothing spent.
    assert [r["step"] for r in _rows(labelled.run_dir, "rounds")] == [
        r["step"] for r in _rows(true.run_dir, "rounds")]
    assert not os.path.exists(os.path.join(true.run_dir, "labels.jsonl")) or not open(
        os.path.join(true.run_dir, "labels.jsonl")).read()
    assert run.feedback.labels_used == 0 and isinstance(run.feedback, TrueRewardRounds)

    # R_theta's targets are the pooled trajectories' true returns, and the agent's reward is
    # the true one on every stored transition.
    assert len(fits) == len(_rows(true.run_dir, "rounds"))
    for skills, targets, pooled_skills, true_returns in fits:
        assert np.array_equal(skills, pooled_skills)
        assert np.allclose(targets, true_returns)
    n = len(run.buffer)
    assert torch.equal(run.buffer.reward[:n], run.buffer.true_reward[:n])


def test_the_true_reward_diagnostic_is_refused_where_it_means_nothing():
    for algo, extra, field in (("sac", {}, "algo sac"), ("rune", {}, "reward.rune"),
                               ("sepoa", {"skill.estimator_refit": False},
                                "cannot go with skill.estimator_refit false")):
        cfg = build_config("dmc:cheetah_run", "tiny", {"algo": algo, "reward.true_reward": True}
                           | extra)
        with pytest.raises(ConfigError, match=field):
            validate(cfg)


def test_r_theta_fitted_only_as_skill_rounds_select_needs_the_skill_rule():
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sepoa", "skill.estimator_refit": False, "feedback.selection": "disagreement"})
    with pytest.raises(ConfigError, match="would never be fitted: keep it true, or select by"):
        validate(cfg)


def test_free_initial_rollouts_come_before_step_0_and_learning_starts_at_once(tmp_path):
    cfg = _tiny(tmp_path, "free", **{"skill.free_initial_rollouts": True,
                                     "skill.initial_rollouts": 4, "skill.reset_critic": False,
                                     "reset_updates": 7})
    run = TrainingRun(cfg, progress=False)
    task_updates: list[bool] = []  # per update: was it the z_task update?
    update = run.policy.agent.update

    def record(batch):
        z = run.policy.task_skill
        task_updates.append(z is not None and bool(
            (batch.skill == torch.as_tensor(z)).all()))
        return update(batch)

    run.policy.agent.update = record
    run.train()
    rounds = _rows(cfg.run_dir, "rounds")
    assert rounds[0]["step"] == "0" == str(first_round_step(cfg))  # on the 4 rollouts
    episodes = _rows(cfg.run_dir, "episodes")
    # 1200 counted steps are 6 episodes of 200; the 4 rollouts come before, uncounted.
    assert [int(r["step"]) for r in episodes] == [200, 400, 600, 800, 1000, 1200]
    assert run.episode == 10
    # The first counted episode learns throughout: 7 updates after the round, then one every
    # 4th step of its 200, on the learned reward. The 7 train the stored skills alone, as the
    # authors' code makes them before its first z_task; then z_task takes every other update.
    assert task_updates[:7] == [False] * 7
    assert task_updates[7:13] == [True, False] * 3  # by parity: the 8th update is odd
    assert int(episodes[0]["updates"]) == 7 + 200 // 4
    assert int(episodes[0]["reward_updates"]) == 7 + 200 // 4
    assert len(run.buffer) == 10 * 200


def test_counted_initial_rollouts_stay_the_default_and_wait_for_the_first_round(tmp_path):
    cfg = _tiny(tmp_path, "counted", **{"skill.initial_rollouts": 3})
    TrainingRun(cfg, progress=False).train()
    episodes = _rows(cfg.run_dir, "episodes")
    assert [int(r["updates"]) for r in episodes[:3]][:2] == [0, 0]
    assert _rows(cfg.run_dir, "rounds")[0]["step"] == "600" == str(first_round_step(cfg))


def test_r_theta_fits_every_complete_replay_episode_when_asked(tmp_path, monkeypatch):
    sizes = []
    fit = ReturnEstimator.fit

    def record(self, skills, returns):
        sizes.append(len(skills))
        return fit(self, skills, returns)

    monkeypatch.setattr(ReturnEstimator, "fit", record)
    cfg = _tiny(tmp_path, "replay", **{"skill.estimator_data": "replay",
                                       "feedback.pool_trajectories": 3})
    run = TrainingRun(cfg, progress=False)
    run.train()
    assert len(run.pool) == 3
    # Round 0 at 600 (3 episodes), round 1 at 1000 (5): each fit on all of them, twice a
    # round (before selecting and after training), not on the 3 pooled.
    assert sizes == [3, 5, 5]


def test_r_theta_is_fitted_only_as_rounds_select_when_asked(tmp_path, monkeypatch):
    fitted_at: list[int] = []
    fit = ReturnEstimator.fit

    def record(self, skills, returns):
        fitted_at.append(run.step)
        return fit(self, skills, returns)

    monkeypatch.setattr(ReturnEstimator, "fit", record)
    cfg = _tiny(tmp_path, "once", **{"skill.estimator_refit": False})
    run = TrainingRun(cfg, progress=False)
    run.train()
    rounds = _rows(cfg.run_dir, "rounds")
    assert [r["step"] for r in rounds] == ["600", "1000"]
    # None at the first round, whose pairs are drawn uniformly; one as the second selects.
    assert fitted_at == [1000]
    # The first z_task came from the unfitted R_theta, as in the authors' code.
    assert rounds[0]["task_skill_predicted"] not in ("", "nan")


def test_replay_episodes_line_up_with_episodes_after_the_ring_wraps():
    buffer = SkillReplayBuffer(2, 1, 3, capacity=6, device=torch.device("cpu"), seed=0)
    for episode in range(5):  # episodes of 2 steps; the ring of 6 holds the last 3
        skill = np.full(3, episode, np.float32)
        for t in range(2):
            buffer.add(np.zeros(2), np.zeros(1), 0.0, float(10 * episode + t), np.zeros(2), skill)
    skills, returns = ReplayEpisodes(buffer, 2).skills_and_returns(None)
    assert sorted(skills[:, 0].tolist()) == [2.0, 3.0, 4.0]
    assert sorted(returns.tolist()) == [41.0, 61.0, 81.0]
    buffer.add(np.zeros(2), np.zeros(1), 0.0, 0.0, np.zeros(2), np.full(3, 5, np.float32))
    # Half of episode 5 overwrote half of episode 2: that block is left out.
    assert sorted(ReplayEpisodes(buffer, 2).skills_and_returns(None)[0][:, 0].tolist()) == [
        3.0, 4.0]
    with pytest.raises(ValueError, match="multiple of the episode length"):
        ReplayEpisodes(buffer, 4).blocks()


def test_the_fixed_sigma_actor_gives_its_weights_no_entropy_gradient_and_bounded_noise():
    torch.manual_seed(0)
    sac = SAC(5, 3, SACConfig(hidden_dim=16, batch_size=8), torch.device("cpu"))
    sac.fix_actor_std(0.2, 0.3, alpha=1.0)
    assert isinstance(sac.actor, FixedStdActor)
    obs = torch.randn(4096, 5)
    action, log_prob = sac.actor.sample(obs)
    assert action.requires_grad and not log_prob.requires_grad  # nothing to differentiate
    mean = torch.tanh(sac.actor.trunk(obs).chunk(2, dim=-1)[0])
    assert (action - mean).abs().max() <= 0.3 + 1e-6  # the updates' noise is clipped
    # Acting, the noise is not clipped (URLB samples with clip=None); actions stay in bounds.
    rng = np.random.default_rng(0)
    o = np.random.default_rng(1).standard_normal(5).astype(np.float32)
    centre = sac.act(o, rng, deterministic=True)
    noisy = np.stack([sac.act(o, rng) for _ in range(2000)])
    assert np.abs(noisy).max() < 1.0 and np.abs(noisy - centre).max() > 0.3
    assert 0.15 < np.median(noisy.std(0)) < 0.25


def test_the_ddpg_actions_bound_passes_the_gradient_straight_through():
    x = torch.tensor([2.0, -3.0, 0.5], requires_grad=True)
    bounded = truncated(x)
    assert bounded.tolist() == pytest.approx([1.0, -1.0, 0.5], abs=1e-5)
    assert bounded.abs().max() < 1.0
    bounded.sum().backward()
    # A hard clamp would give the first two nothing: a saturated mean could never come back.
    assert x.grad is not None and x.grad.tolist() == [1.0, 1.0, 1.0]


def test_the_ddpg_actors_temperature_is_tuned_from_1_as_the_authors_code_tunes_it():
    torch.manual_seed(0)
    sac = SAC(5, 3, SACConfig(hidden_dim=16, batch_size=8), torch.device("cpu"))
    sac.fix_actor_std(0.2, 0.3, alpha=1.0)
    assert sac.alpha.item() == pytest.approx(1.0)
    batch_obs = torch.randn(8, 5)
    for _ in range(20):
        sac.update(Batch(batch_obs, torch.rand(8, 3) * 2 - 1, torch.randn(8, 1), batch_obs))
    # A fixed sigma of 0.2 has far more log-probability than the target entropy -|A| allows:
    # alpha falls, step by step, as it does in the authors' fine-tuning.
    assert sac.alpha.item() < 0.999


def test_a_sepoa_run_fine_tunes_with_the_ddpg_actor_when_asked(tmp_path):
    cfg = _tiny(tmp_path, "ddpg", **{"skill.actor": "ddpg", "steps": 800})
    run = TrainingRun(cfg, progress=False)
    run.train()
    assert isinstance(run.agent.sac.actor, FixedStdActor)
    alphas = [float(r["alpha"]) for r in _rows(cfg.run_dir, "episodes") if r["alpha"]]
    assert alphas and alphas[-1] < 1.0
    with pytest.raises(ConfigError, match="skill.actor"):
        validate(_tiny(tmp_path, "bad", **{"skill.actor": "td3"}))


def test_every_authors_option_at_once_runs_and_keeps_the_update_budget(tmp_path):
    authors = authors_overrides()
    cfg = _tiny(tmp_path, "authors", **authors | {"skill.initial_rollouts": 3,
                                                  "reset_updates": 5})
    run = TrainingRun(cfg, progress=False)
    run.train()
    rounds = _rows(cfg.run_dir, "rounds")
    assert [r["step"] for r in rounds] == ["0", "400", "800"]
    assert isinstance(run.agent.sac.actor, FixedStdActor)
    # One update every 4th step from step 0, and the 5 after the first round.
    assert int(_rows(cfg.run_dir, "episodes")[-1]["updates"]) == 5 + 1200 // 4

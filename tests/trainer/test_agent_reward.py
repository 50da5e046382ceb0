"""Which reward the agent stores and trains on, at tiny sizes: the oracle's true reward,
PEBBLE's state-entropy reward before the first round, r_hat after it, and RUNE's bonus."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from runvocab.config import build_config
from trainer.agent_reward import AgentReward, TrueReward, make_agent_reward
from trainer.feedback import LabelLog, NoFeedback, PreferenceFeedback
from trainer.replay_buffer import ReplayBuffer
from trainer.reward_model import RewardModel
from trainer.teachers import make_teacher

OBS, ACT = 3, 2
CPU = torch.device("cpu")


def _cfg(algo: str, **overrides):
    return build_config("dmc:cheetah_run", "tiny", {"algo": algo} | overrides)


def _buffer(n: int = 64) -> ReplayBuffer:
    rng = np.random.default_rng(0)
    buffer = ReplayBuffer(OBS, ACT, 128, CPU, seed=0)
    for _ in range(n):
        obs = rng.normal(size=OBS).astype(np.float32)
        buffer.add(obs, rng.uniform(-1, 1, ACT).astype(np.float32), 0.0, float(obs.sum()),
                   rng.normal(size=OBS).astype(np.float32))
    return buffer


def _feedback(cfg, tmp_path) -> PreferenceFeedback:
    model = RewardModel(OBS, ACT, cfg.reward, CPU, 0)
    teacher = make_teacher(cfg.teacher, 0, cfg.feedback.segment_length, 100)
    return PreferenceFeedback(cfg.feedback, model, teacher, "scripted:noisy",
                              LabelLog(str(tmp_path / "labels.jsonl")), np.random.default_rng(1))


def test_the_oracle_stores_and_trains_on_the_true_reward():
    cfg, buffer = _cfg("sac"), _buffer()
    reward = make_agent_reward(cfg, buffer, NoFeedback(), CPU)
    assert isinstance(reward, TrueReward)
    assert reward.at_step(np.zeros(OBS), np.zeros(ACT), 1.25) == 1.25
    batch = buffer.sample(8)
    assert reward.batch(batch, step=10) is batch
    assert not reward.learned and reward.unsupervised_steps == 0
    assert reward.state_dict() == {} and reward.episode_row(10) == {}


def test_before_the_first_round_pebble_trains_on_normalised_state_entropy(tmp_path):
    cfg, buffer = _cfg("pebble"), _buffer()
    reward = make_agent_reward(cfg, buffer, _feedback(cfg, tmp_path), CPU)
    assert isinstance(reward, AgentReward)
    assert reward.unsupervised_steps == cfg.unsup_steps
    assert reward.at_step(np.ones(OBS, np.float32), np.ones(ACT, np.float32), 3.0) == 0.0
    batch = buffer.sample(16)
    trained = reward.batch(batch, step=10)
    distance = reward.entropy_distance(batch.next_obs)
    torch.testing.assert_close(trained.reward, (distance / reward.entropy_stats.std)[:, None])
    assert not reward.learned


def test_after_the_first_round_new_transitions_store_r_hat(tmp_path):
    cfg, buffer = _cfg("pebble"), _buffer()
    feedback = _feedback(cfg, tmp_path)
    reward = make_agent_reward(cfg, buffer, feedback, CPU)
    feedback.rounds = 1
    assert reward.learned
    obs, action = np.full(OBS, 0.5, np.float32), np.full(ACT, -0.5, np.float32)
    expected = feedback.model.reward(torch.from_numpy(obs)[None], torch.from_numpy(action)[None])
    assert reward.at_step(obs, action, 3.0) == pytest.approx(float(expected[0]), abs=1e-6)
    batch = buffer.sample(8)
    assert torch.equal(reward.batch(batch, step=500).reward, batch.reward)  # no bonus


def test_runes_bonus_fades_from_the_step_the_first_round_closed(tmp_path):
    cfg, buffer = _cfg("rune"), _buffer()
    feedback = _feedback(cfg, tmp_path)
    reward = make_agent_reward(cfg, buffer, feedback, CPU)
    assert isinstance(reward, AgentReward)
    feedback.rounds = 1
    assert reward.episode_row(400) == {}  # no beta before the agent trains on r_hat
    reward.first_round_closed(400)
    assert reward.episode_row(400) == {"rune_beta": cfg.reward.rune_beta0}
    assert reward.rune_beta(1400) < reward.rune_beta(400)
    batch = buffer.sample(8)
    std = feedback.model.reward_std(batch.obs, batch.action)
    torch.testing.assert_close(reward.batch(batch, step=1400).reward,
                               batch.reward + reward.rune_beta(1400) * std[:, None])


def test_the_reward_state_survives_a_checkpoint(tmp_path):
    cfg, buffer = _cfg("rune"), _buffer()
    reward = make_agent_reward(cfg, buffer, _feedback(cfg, tmp_path), CPU)
    reward.batch(buffer.sample(16), step=5)  # moves the running std
    reward.first_round_closed(300)
    restored = make_agent_reward(cfg, buffer, _feedback(cfg, tmp_path), CPU)
    restored.load_state_dict(reward.state_dict())
    assert isinstance(restored, AgentReward) and isinstance(reward, AgentReward)
    assert restored.start_step == 300
    assert restored.entropy_stats.std == reward.entropy_stats.std != 1.0

"""The agent as the loop sees it, at tiny sizes: how updates are counted, S-EPOA's turns
between stored skills and z_task, and which skill an episode and an evaluation act with."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from runvocab.config import build_config
from trainer.hooks import RunHooks
from trainer.policies import EpisodeMeta, Policy, SkillPolicy, make_policy

OBS, ACT = 3, 2
CPU = torch.device("cpu")


def _policy(algo: str, **overrides) -> Policy:
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": algo, "skill.pretrain_steps": 0, "skill.estimator_hidden_dim": 16,
        "skill.estimator_steps": 5, "skill.task_skill_samples": 8} | overrides)
    policy = make_policy(cfg, OBS, ACT, CPU, RunHooks())
    rng = np.random.default_rng(0)
    for _ in range(64):  # transitions, each under its episode's skill
        meta = policy.episode_meta(rng)
        policy.buffer.add(rng.normal(size=OBS).astype(np.float32),
                          rng.uniform(-1, 1, ACT).astype(np.float32), 0.1, 0.1,
                          rng.normal(size=OBS).astype(np.float32), meta.skill)
    return policy


def _batches(policy: Policy):
    return lambda: policy.buffer.sample(policy.cfg.sac.batch_size)


def test_every_update_is_counted_and_those_on_r_hat_apart():
    policy = _policy("pebble")
    for learned in (False, False, True):
        metrics = policy.update(_batches(policy), learned)
        assert "critic_loss" in metrics
    assert (policy.updates, policy.reward_updates) == (3, 1)
    restored = _policy("pebble")
    restored.load_state_dict(policy.state_dict())
    assert (restored.updates, restored.reward_updates) == (3, 1)


def test_sac_acts_on_the_observation_alone():
    policy = _policy("sac")
    obs = np.ones(OBS, np.float32)
    assert policy.episode_meta(np.random.default_rng(0)) == EpisodeMeta()
    action = policy.act(obs, EpisodeMeta(), np.random.default_rng(0), deterministic=True)
    assert action.shape == (ACT,) and np.all(np.abs(action) < 1)


def test_sepoa_waits_for_a_learned_reward_before_its_first_update():
    policy = _policy("sepoa")
    assert policy.update(_batches(policy), learned=False) == {}
    assert policy.updates == 0 and policy.random_seed_steps == 0


@pytest.mark.parametrize("task_skill_update", [True, False])
def test_sepoa_updates_take_turns_on_stored_skills_and_on_z_task(monkeypatch,
                                                                  task_skill_update):
    policy = _policy("sepoa", **{"skill.task_skill_update": task_skill_update})
    assert isinstance(policy, SkillPolicy)
    policy.task_skill = policy.skills.sample_skills(np.random.default_rng(9), 1)[0]
    trained_skills = []
    update = policy.agent.update
    monkeypatch.setattr(policy.agent, "update",
                        lambda batch: trained_skills.append(batch.skill) or update(batch))
    metrics = [policy.update(_batches(policy), learned=True) for _ in range(4)]
    z_task = torch.as_tensor(policy.task_skill)
    on_z_task = [bool((skills == z_task).all()) for skills in trained_skills]
    assert on_z_task == ([False, True, False, True] if task_skill_update else [False] * 4)
    # A z_task update logs its own metrics beside the last stored-skill update's.
    assert ("task_critic_loss" in metrics[1]) == task_skill_update
    assert policy.updates == policy.reward_updates == 4


def test_sepoa_acts_with_a_random_skill_until_z_task_then_evaluates_with_z_task():
    policy = _policy("sepoa")
    assert isinstance(policy, SkillPolicy)
    rng = np.random.default_rng(3)
    first, second = policy.episode_meta(rng), policy.episode_meta(rng)
    assert first.skill is not None and second.skill is not None
    assert not np.array_equal(first.skill, second.skill)
    assert policy.eval_meta(first) is first  # no z_task yet: the episode's own skill

    skills = policy.skills.sample_skills(rng, 32)
    policy.estimator.fit(skills, skills.sum(axis=1))
    policy.round_closed(np.random.default_rng(4))
    candidates = policy.skills.sample_skills(np.random.default_rng(4), 8)
    assert np.array_equal(policy.task_skill, policy.estimator.best_skill(candidates))
    assert np.array_equal(policy.episode_meta(rng).skill, policy.task_skill)
    assert np.array_equal(policy.eval_meta(first).skill, policy.task_skill)

    obs = np.zeros(OBS, np.float32)
    with pytest.raises(AssertionError):
        policy.act(obs, EpisodeMeta(), rng)
    actions = [policy.act(obs, meta, rng, deterministic=True) for meta in (first, second)]
    assert not np.allclose(*actions)  # pi(a|s,z) depends on z

"""S-EPOA online: R_theta, the skill-based score, z_task, skill-trajectory alignment, and a tiny
end-to-end run through the CLI."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from runvocab.config import SkillConfig, build_config
from trainer.loop import TrainingRun
from trainer.return_estimator import ReturnEstimator, skill_scores

CPU = torch.device("cpu")


def _estimator(skill_dim: int = 4) -> ReturnEstimator:
    torch.manual_seed(0)
    return ReturnEstimator(skill_dim, SkillConfig(estimator_hidden_dim=64, estimator_steps=500,
                                                  estimator_lr=3e-3), CPU)


def test_return_estimator_fits_a_planted_skill_to_return_map():
    rng = np.random.default_rng(0)
    skills = rng.standard_normal((100, 4)).astype(np.float32)
    returns = 300 * skills[:, 0] - 100 * skills[:, 2] + 50  # on any scale: targets are min-maxed
    estimator = _estimator()
    estimator.fit(skills, returns)
    held_out = rng.standard_normal((200, 4)).astype(np.float32)
    predicted = estimator.predict(held_out).numpy()
    truth = 3 * held_out[:, 0] - held_out[:, 2]
    assert np.corrcoef(predicted, truth)[0, 1] > 0.9
    assert 0 <= predicted.min() and predicted.max() <= 1.05  # the targets lie in [0, 1]


def test_z_task_is_the_candidate_with_the_highest_estimate():
    rng = np.random.default_rng(1)
    estimator = _estimator()
    estimator.fit(rng.standard_normal((50, 4)).astype(np.float32), rng.random(50))
    candidates = rng.standard_normal((50, 4)).astype(np.float32)
    best = estimator.best_skill(candidates)
    assert np.array_equal(best, candidates[int(estimator.predict(candidates).argmax())])


def test_skill_score_prefers_the_largest_return_gap_when_spreads_tie():
    value0 = torch.tensor([0.1, 0.2, 0.9, 0.5])
    value1 = torch.tensor([0.2, 0.2, 0.1, 0.4])  # gaps 0.1, 0.0, 0.8, 0.1
    p = torch.tensor([[0.3, 0.3, 0.3, 0.3], [0.7, 0.7, 0.7, 0.7]])  # the same spread everywhere
    for spread in ("var", "std"):
        scores = skill_scores(value0, value1, p, spread)
        assert int(scores.argmax()) == 2
        assert torch.allclose(scores, 1 + torch.tensor([0.125, 0.0, 1.0, 0.125]))


def test_skill_score_prefers_the_largest_spread_when_gaps_tie():
    value0, value1 = torch.tensor([0.5, 0.5, 0.5]), torch.tensor([0.1, 0.1, 0.1])
    p = torch.tensor([[0.5, 0.1, 0.45], [0.5, 0.9, 0.55]])  # spreads 0, 0.4, 0.05
    assert int(skill_scores(value0, value1, p, "var").argmax()) == 1
    # I = (1 + gap') (1 + spread'), both min-max normalised over the candidates.
    expected = 1 + torch.tensor([0.0, 1.0, 0.05 ** 2 / 0.4 ** 2])
    assert torch.allclose(skill_scores(value0, value1, p, "var"), expected)
    with pytest.raises(ValueError, match="spread"):
        skill_scores(value0, value1, p, "mad")


# A SAC update every 4 steps and a small R_theta: the same episodes, rounds and skills, in a
# third of the time (the updates and R_theta's fits are most of a tiny run's time).
FAST = {"update_every": 4, "skill.estimator_hidden_dim": 32, "skill.estimator_steps": 50}


def _tiny(tmp_path, **overrides):
    base = {"algo": "sepoa", "steps": 1200, "threads": 1, "teacher.eps": 0.3,
            "skill.snapshot_dir": str(tmp_path / "snapshots"),
            "run_dir": str(tmp_path / "run")} | FAST
    return build_config("dmc:cheetah_run", "tiny", base | overrides)


def test_each_trajectory_keeps_the_skill_it_was_generated_with_after_fifo_eviction(tmp_path):
    cfg = _tiny(tmp_path, **{"feedback.pool_trajectories": 3, "skill.pretrain_steps": 0,
                             "skill.task_skill_draw": "episode"})
    run = TrainingRun(cfg, progress=False)
    run.train()
    assert len(run.pool) == 3 and run.episode == 6  # three evicted
    for traj in run.pool.trajectories:
        # Episode i filled buffer rows [i * 200, (i + 1) * 200): its skill is in every row.
        rows = run.buffer.skill[traj.id * 200:(traj.id + 1) * 200].numpy()
        assert np.array_equal(rows, np.broadcast_to(traj.skill, rows.shape)), traj.id
    skills = [tuple(t.skill) for t in run.pool.trajectories]
    assert len(set(skills)) == 3  # a fresh z_task each episode


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_tiny_sepoa_run_pretrains_once_then_learns_from_labels_by_the_skill_rule(tmp_path):
    command = [sys.executable, "-m", "sepoa", "train", "--task", "dmc:cheetah_run",
               "--algo", "sepoa", "--preset", "tiny", "--steps", "1200", "--eps", "0.3",
               "--threads", "1", "--no-progress",
               "--skill.snapshot_dir", str(tmp_path / "snapshots")]
    command += [f"--{field}={value}" for field, value in FAST.items()]
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    first = subprocess.run(command + ["--run-dir", str(tmp_path / "a")], env=env,
                           capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    assert "pretraining aps for 300 steps first" in first.stderr
    [snapshot] = (tmp_path / "snapshots").glob("dmc-cheetah_run-aps-300-s0-*.pt")

    rounds = _rows(tmp_path / "a" / "rounds.csv")
    assert [int(r["labels_used"]) for r in rounds] == [10, 20]
    assert all(0 <= float(r["distinguishable_ratio"]) <= 1 for r in rounds)
    # z_task is drawn again as each round closes; the first has no predecessor to compare.
    assert math.isnan(float(rounds[0]["task_skill_cosine"]))
    assert -1 - 1e-6 <= float(rounds[1]["task_skill_cosine"]) <= 1 + 1e-6
    assert math.isfinite(float(rounds[1]["task_skill_gain"]))
    assert all(math.isfinite(float(r["task_skill_predicted"])) for r in rounds)
    with open(tmp_path / "a" / "labels.jsonl") as f:
        labels = [json.loads(line) for line in f]
    assert [lab["rule"] for lab in labels] == ["uniform"] * 10 + ["skill"] * 10
    assert json.loads(first.stdout.splitlines()[-1])["labels_used"] == 20

    # With a fixed snapshot seed another seed loads the same snapshot instead of pretraining
    # its own (one episode shows it).
    second = subprocess.run(command + ["--run-dir", str(tmp_path / "b"), "--seed", "1",
                                       "--steps", "200", "--skill.snapshot_seed", "0"],
                            env=env, capture_output=True, text=True, timeout=300)
    assert second.returncode == 0, second.stderr
    assert "pretraining" not in second.stderr
    assert json.loads(second.stdout.splitlines()[-1])["step"] == 200


def test_a_sepoa_run_stopped_inside_a_round_resumes_like_an_uninterrupted_one(tmp_path,
                                                                             monkeypatch):
    shared = {"skill.pretrain_steps": 0}
    reference = _tiny(tmp_path, **shared, run_dir=str(tmp_path / "reference"))
    TrainingRun(reference, progress=False).train()

    cfg = _tiny(tmp_path, **shared, run_dir=str(tmp_path / "cut"))
    finish = TrainingRun._finish_round

    def die_in_second_round(self, answers):
        if self.feedback.rounds == 1:
            raise KeyboardInterrupt
        finish(self, answers)

    monkeypatch.setattr(TrainingRun, "_finish_round", die_in_second_round)
    with pytest.raises(KeyboardInterrupt):
        TrainingRun(cfg, progress=False).train()
    monkeypatch.setattr(TrainingRun, "_finish_round", finish)
    TrainingRun(cfg, resume=True, progress=False).train()

    def strip(path):
        with open(path) as f:
            return [{k: v for k, v in json.loads(line).items() if k != "answered_at"}
                    for line in f]

    assert strip(tmp_path / "cut" / "labels.jsonl") == strip(
        tmp_path / "reference" / "labels.jsonl")
    assert _rows(tmp_path / "cut" / "episodes.csv")[-1]["return"] == _rows(
        tmp_path / "reference" / "episodes.csv")[-1]["return"]


def test_skill_selection_is_refused_without_skills(tmp_path):
    with pytest.raises(ValueError, match="use algo sepoa"):
        TrainingRun(build_config("dmc:cheetah_run", "tiny", {
            "algo": "pebble", "feedback.selection": "skill",
            "run_dir": str(tmp_path / "x")}), progress=False)


def test_the_disagreement_ablation_still_acts_with_z_task(tmp_path):
    cfg = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "feedback.selection": "disagreement"})
    run = TrainingRun(cfg, progress=False)
    run.train()
    with open(tmp_path / "run" / "labels.jsonl") as f:
        rules = [json.loads(line)["rule"] for line in f]
    assert rules == ["uniform"] * 10 + ["disagreement"] * 10
    estimator = run.feedback.estimator
    assert estimator.fitted  # refitted after each round, whatever the selection rule
    candidates = run.policy.skills.sample_skills(np.random.default_rng(5), 50)
    assert np.array_equal(estimator.best_skill(candidates),
                          candidates[int(estimator.predict(candidates).argmax())])


@pytest.mark.parametrize("backend", ["diayn", "cic"])
def test_other_skill_backends_run_online_behind_the_same_interface(tmp_path, backend):
    cfg = _tiny(tmp_path, **{"skill.backend": backend, "skill.pretrain_steps": 0})
    run = TrainingRun(cfg, progress=False)
    summary = run.train()
    assert summary["labels_used"] == 20
    dims = {"diayn": 16, "cic": 64}
    assert all(t.skill.shape == (dims[backend],) for t in run.pool.trajectories)


def _labels(run_dir):
    with open(os.path.join(run_dir, "labels.jsonl")) as f:
        return [json.loads(line) for line in f]


def test_round_zero_waits_for_the_initial_rollouts_and_spans_them(tmp_path):
    cfg = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "skill.initial_rollouts": 4})
    run = TrainingRun(cfg, progress=False)
    run.train()
    round0 = [lab for lab in _labels(cfg.run_dir) if lab["round"] == 0]
    assert {lab["step"] for lab in round0} == {800}  # after 4 episodes of 200, not at 200
    used = {t for lab in round0 for t in (lab["trajectory0"], lab["trajectory1"])}
    assert used == {0, 1, 2, 3}
    skills = {tuple(t.skill) for t in run.pool.trajectories if t.id < 4}
    assert len(skills) == 4  # each initial rollout had its own random skill
    rounds = _rows(os.path.join(cfg.run_dir, "rounds.csv"))
    assert int(rounds[0]["trajectory_pairs"]) > 1
    assert 0 < float(rounds[0]["max_trajectory_share"]) <= 1
    assert all(-1 <= float(r["reward_corr"]) <= 1 for r in rounds)
    with pytest.raises(ValueError, match="initial_rollouts 5 exceeds feedback.pool_trajectories 4"):
        TrainingRun(_tiny(tmp_path, **{"skill.initial_rollouts": 5,
                                        "feedback.pool_trajectories": 4,
                                        "run_dir": str(tmp_path / "x")}), progress=False)


def test_updates_after_the_first_round_take_turns_on_stored_skills_and_on_z_task(tmp_path,
                                                                              monkeypatch):
    from trainer.skills.agent import SkillAgent

    seen = []
    update = SkillAgent.update

    def spy(agent, batch):
        seen.append((batch.skill.clone(), run.policy.task_skill.copy()))
        return update(agent, batch)

    monkeypatch.setattr(SkillAgent, "update", spy)
    run = TrainingRun(_tiny(tmp_path, **{"skill.pretrain_steps": 0}), progress=False)
    run.train()
    assert len(seen) > 2  # a stored-skill update and a z_task one, in turn
    assert np.array_equal(run.meta.skill, run.policy.task_skill)  # the skill that acts is z_task
    stored, task = seen[0::2], seen[1::2]
    for skills, acting in task:
        assert torch.equal(skills, torch.as_tensor(acting).expand_as(skills))
    # The stored-skill updates carry the skills of many episodes.
    assert any(len(torch.unique(skills, dim=0)) > 1 for skills, _ in stored)

    seen.clear()
    off = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "skill.task_skill_update": False,
                             "run_dir": str(tmp_path / "off")})
    run = TrainingRun(off, progress=False)
    run.train()
    assert seen and not any(len(torch.unique(s, dim=0)) == 1 for s, _ in seen)


def _weights(module):
    return {k: v.clone() for k, v in module.state_dict().items()}


@pytest.mark.parametrize("reset", [True, False])
def test_the_first_round_resets_the_critic_only_and_keeps_the_actor(tmp_path, monkeypatch,
                                                                    reset):
    cfg = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "skill.reset_critic": reset,
                             "reset_updates": 0, "steps": 700})
    run = TrainingRun(cfg, progress=False)
    sac = run.agent.sac
    nets = {"actor": sac.actor, "critic": sac.critic, "target": sac.critic_target}
    finish, before, after = TrainingRun._finish_round, {}, {}

    def watch(self, answers):
        before.update({name: _weights(net) for name, net in nets.items()})
        finish(self, answers)
        after.update({name: _weights(net) for name, net in nets.items()})

    monkeypatch.setattr(TrainingRun, "_finish_round", watch)
    run.train()
    assert run.feedback.rounds == 1
    for name in nets:
        same = all(torch.equal(v, after[name][k]) for k, v in before[name].items())
        assert same == (name == "actor" or not reset), name
    torch.testing.assert_close(after["critic"], after["target"])


def test_z_task_is_held_between_refits_or_drawn_each_episode(tmp_path):
    skills = {}
    for draw in ("refit", "episode"):
        cfg = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "skill.task_skill_draw": draw,
                                 "run_dir": str(tmp_path / draw)})
        run = TrainingRun(cfg, progress=False)
        run.train()
        skills[draw] = [tuple(t.skill) for t in run.pool.trajectories]
    # Round 0 closes after episode 3 (R_theta fitted), round 1 after episode 5 (refitted).
    held = skills["refit"]
    assert len(set(held[:3])) == 3 and held[3] == held[4] != held[5]
    assert len(set(skills["episode"])) == 6


def test_a_checkpoint_from_before_these_changes_is_refused_with_the_reason(tmp_path):
    from trainer.checkpoint import load_checkpoint, save_checkpoint

    cfg = _tiny(tmp_path, **{"skill.pretrain_steps": 0, "steps": 400})
    TrainingRun(cfg, progress=False).train()
    path = os.path.join(cfg.run_dir, "checkpoint.pt")
    state = load_checkpoint(path)
    del state["loop_version"]
    save_checkpoint(path, state)
    with pytest.raises(ValueError, match="training-loop version 1.*start a new run"):
        TrainingRun(dataclasses.replace(cfg, steps=800), resume=True, progress=False)

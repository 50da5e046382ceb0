"""experiments.diagnostics.skill_choice: z_task against random skills on an S-EPOA run's
checkpoint."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import sys

import numpy as np
import pytest

from experiments.diagnostics import skill_choice
from runvocab.config import build_config
from trainer.envs import make_env
from trainer.loop import TrainingRun
from trainer.policies import EpisodeMeta


def _digests(folder) -> dict[str, str]:
    return {name: hashlib.sha256((folder / name).read_bytes()).hexdigest()
            for name in sorted(os.listdir(folder)) if (folder / name).is_file()}


@pytest.fixture(scope="module")
def sepoa_run(tmp_path_factory):
    """A tiny S-EPOA run with two rounds, left with its checkpoint as a stopped run is."""
    root = tmp_path_factory.mktemp("skill_choice")
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sepoa", "steps": 1200, "threads": 1, "teacher.eps": 0.3,
        "skill.pretrain_steps": 0, "update_every": 4, "skill.estimator_hidden_dim": 32,
        "skill.estimator_steps": 50, "run_dir": str(root / "run")})
    run = TrainingRun(cfg, progress=False)
    run.train()
    return root / "run", run


def test_z_task_is_measured_as_the_loop_evaluates_it_and_the_run_is_only_read(sepoa_run):
    folder, run = sepoa_run
    before = _digests(folder)
    choice = skill_choice.measure(str(folder), skills=3, episodes=1, threads=1, seed=7)
    assert _digests(folder) == before

    # The loop's own evaluation of z_task, one episode on a fresh env of the same seed.
    run.cfg = dataclasses.replace(run.cfg, eval_episodes=1)
    run.eval_env = make_env(run.cfg.task, 7, run.cfg.episode_length or None)
    assert choice.task_return == pytest.approx(run.evaluate()["return"], rel=1e-9)

    assert choice.step == 1200
    assert choice.predicted.shape == choice.learned_returns.shape == choice.returns.shape == (3,)
    assert 1 <= choice.pool_skills <= choice.pool_trajectories == len(run.pool)
    assert choice.pick_return == choice.returns[int(np.argmax(choice.predicted))]
    assert choice.learned_pick_return == choice.returns[int(np.argmax(choice.learned_returns))]
    assert 0 <= choice.task_beats <= 1


def test_the_command_prints_a_row_per_run_and_writes_every_skill(sepoa_run, tmp_path,
                                                                 monkeypatch, capsys):
    folder, _ = sepoa_run
    out = tmp_path / "skills.csv"
    monkeypatch.setattr(sys, "argv", ["skill_choice.py", str(folder), "--skills", "2",
                                      "--csv", str(out)])
    skill_choice.main()
    header, row = capsys.readouterr().out.splitlines()
    assert header.startswith("run  step") and row.startswith(f"{folder}  1200  ")
    lines = out.read_text().splitlines()
    assert lines[0] == "run,step,skill,predicted,learned_return,return"
    assert [line.split(",")[2] for line in lines[1:]] == ["0", "1", "z_task"]


def test_runs_it_cannot_measure_are_refused_with_the_reason(sepoa_run, tmp_path):
    with pytest.raises(SystemExit, match="no checkpoint.pt"):
        skill_choice.measure(str(tmp_path), skills=2, episodes=1, threads=1, seed=0)
    pebble = tmp_path / "pebble"
    TrainingRun(build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "steps": 200, "threads": 1, "run_dir": str(pebble)}),
        progress=False).train()
    with pytest.raises(SystemExit, match="a pebble run; only S-EPOA acts with skills"):
        skill_choice.measure(str(pebble), skills=2, episodes=1, threads=1, seed=0)


def test_rank_correlation_uses_average_ranks_for_ties():
    assert skill_choice.spearman(np.array([1.0, 2, 3]), np.array([10.0, 20, 30])) == 1
    assert skill_choice.spearman(np.array([1.0, 2, 3]), np.array([3.0, 2, 1])) == -1
    # Ranks of [5, 5, 9] are [0.5, 0.5, 2]: correlated with [0, 1, 2] at 0.866.
    assert skill_choice.spearman(np.array([5.0, 5, 9]), np.array([0.0, 1, 2])) == pytest.approx(
        np.corrcoef([0.5, 0.5, 2], [0, 1, 2])[0, 1])
    assert np.isnan(skill_choice.spearman(np.array([1.0, 1, 1]), np.array([0.0, 1, 2])))


def test_a_skills_learned_return_sums_r_hat_over_each_of_its_episodes(sepoa_run, monkeypatch):
    _, run = sepoa_run
    env = make_env(run.cfg.task, 3, run.cfg.episode_length or None)
    monkeypatch.setattr(run.feedback.model, "reward", lambda obs, action: action[:, 0] + 2)
    skill = run.policy.task_skill
    true_return, learned = skill_choice.skill_returns(run, env, skill, 2,
                                                      np.random.default_rng(0))

    # The same two episodes again, their actions summed by hand.
    env = make_env(run.cfg.task, 3, run.cfg.episode_length or None)
    totals, sums = [], []
    for _ in range(2):
        obs, done, total, summed = env.reset(), False, 0.0, 0.0
        while not done:
            action = run.policy.act(obs, EpisodeMeta(skill), np.random.default_rng(0), True)
            summed += float(action[0]) + 2
            result = env.step(action)
            obs, done, total = result.obs, result.done, total + result.reward
        totals.append(total)
        sums.append(summed)
    assert true_return == pytest.approx(np.mean(totals), rel=1e-9)
    assert learned == pytest.approx(np.mean(sums), rel=1e-5)

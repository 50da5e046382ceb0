"""experiments.diagnostics.reward_crosscheck: every run's reward model judges every run's
policy."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import sys

import numpy as np
import pytest
import torch

from experiments.diagnostics import reward_crosscheck
from runvocab.config import build_config
from trainer.envs import make_env
from trainer.loop import TrainingRun
from trainer.reward_model import RewardModel


def _digests(folder) -> dict[str, str]:
    return {name: hashlib.sha256((folder / name).read_bytes()).hexdigest()
            for name in sorted(os.listdir(folder)) if (folder / name).is_file()}


def _train(root, variant: str, algo: str, steps: int) -> tuple:
    folder = root / variant / "eps0.3" / "s0"
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": algo, "steps": steps, "threads": 1, "teacher.eps": 0.3, "run_dir": str(folder)})
    run = TrainingRun(cfg, progress=False)
    run.train()
    return folder, run


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A tiny PEBBLE run past its first round and a tiny SAC oracle, with their checkpoints."""
    root = tmp_path_factory.mktemp("crosscheck")
    return _train(root, "PEBBLE", "pebble", 600), _train(root, "SAC", "sac", 400)


def test_each_policy_plays_as_the_loop_evaluates_it_and_the_runs_are_only_read(runs):
    (pebble_dir, pebble), (sac_dir, _) = runs
    before = {d: _digests(d) for d in (pebble_dir, sac_dir)}
    played = [reward_crosscheck.load(str(d), episodes=2, seed=5, threads=1)
              for d in (pebble_dir, sac_dir)]
    assert {d: _digests(d) for d in (pebble_dir, sac_dir)} == before

    assert [(p.label, p.algo, p.step) for p in played] == [
        ("PEBBLE/eps0.3/s0", "pebble", 600), ("SAC/eps0.3/s0", "sac", 400)]
    assert played[0].model is not None and played[1].model is None
    for e in played[0].episodes:
        assert e.observations.shape == (201, 17) and e.actions.shape == (200, 6)
        assert e.rewards.shape == (200,)

    # The loop's own evaluation of the same policy: two episodes on a fresh env of the seed.
    pebble.cfg = dataclasses.replace(pebble.cfg, eval_episodes=2)
    pebble.eval_env = make_env(pebble.cfg.task, 5, pebble.cfg.episode_length or None)
    assert played[0].true_return == pytest.approx(pebble.evaluate()["return"], rel=1e-6)


def test_a_models_learned_return_sums_r_hat_over_the_episode(runs, monkeypatch):
    (pebble_dir, _), _ = runs
    played = reward_crosscheck.load(str(pebble_dir), episodes=2, seed=0, threads=1)
    monkeypatch.setattr(played.model, "reward", lambda obs, action: action[:, 0] + 2)
    episode = played.episodes[1]
    assert reward_crosscheck.learned_return(played.model, episode) == pytest.approx(
        float(episode.actions[:, 0].astype(np.float64).sum() + 2 * 200), rel=1e-5)


def test_judging_ranks_by_the_models_scores_and_the_truth(runs, monkeypatch):
    (pebble_dir, _), (sac_dir, _) = runs
    played = [reward_crosscheck.load(str(d), episodes=2, seed=0, threads=1)
              for d in (pebble_dir, sac_dir)]
    model = played[0].model
    # A model whose reward is minus the ninth observation: its scores are known by hand.
    monkeypatch.setattr(model, "reward", lambda obs, action: -obs[:, 8])
    judged = reward_crosscheck.judge(played, pairs=50, segment=20, seed=0)
    assert list(judged) == [0]  # the oracle has no reward model
    j = judged[0]
    by_hand = [np.mean([-e.observations[:-1, 8].astype(np.float64).sum() for e in p.episodes])
               for p in played]
    np.testing.assert_allclose(j.learned_returns, by_hand, rtol=1e-5)
    assert j.own_rank == (1 if by_hand[0] >= by_hand[1] else 2)
    assert j.favourite == int(np.argmax(by_hand))
    truth = [p.true_return for p in played]
    assert j.own_true_rank == (1 if truth[0] >= truth[1] else 2)
    assert -1 <= j.episode_rank_corr <= 1 and -1 <= j.step_corr <= 1
    assert 0 <= j.pair_accuracy <= 1 and 0 <= j.own_pair_accuracy <= 1


def test_own_rank_counts_the_policies_scored_above_it():
    j = reward_crosscheck.Judgement(
        learned_returns=np.array([3.0, 5.0, 1.0, 3.0]), own=0, own_true_rank=4,
        policy_rank_corr=0.0, episode_rank_corr=0.0, pair_accuracy=0.5, own_pair_accuracy=0.5,
        step_corr=0.0)
    assert j.own_rank == j.rank_of(0) == j.rank_of(3) == 2  # a tie does not rank above it
    assert j.rank_of(1) == 1 and j.rank_of(2) == 4
    assert j.favourite == 1


def test_the_command_prints_every_model_and_writes_every_score(runs, tmp_path, monkeypatch,
                                                                capsys):
    (pebble_dir, _), (sac_dir, _) = runs
    out = tmp_path / "scores.csv"
    monkeypatch.setattr(sys, "argv", [
        "reward_crosscheck.py", str(pebble_dir), str(sac_dir), "--episodes", "2",
        "--pairs", "30", "--segment", "20", "--csv", str(out)])
    reward_crosscheck.main()
    printed = capsys.readouterr().out
    assert printed.startswith("2 policies, 2 episodes each")
    assert "\nPEBBLE/eps0.3/s0  | " in printed and "\nSAC/eps0.3/s0  | " not in printed
    assert "\nPEBBLE  1  " in printed  # the by-variant summary
    lines = out.read_text().splitlines()
    assert lines[0] == "model,policy,policy_algo,learned_return,true_return"
    assert [line.split(",")[:3] for line in lines[1:]] == [
        ["PEBBLE/eps0.3/s0", "PEBBLE/eps0.3/s0", "pebble"],
        ["PEBBLE/eps0.3/s0", "SAC/eps0.3/s0", "sac"]]

    monkeypatch.setattr(sys, "argv", [
        "reward_crosscheck.py", str(pebble_dir), str(sac_dir), "--episodes", "2",
        "--pairs", "30", "--segment", "20", "--refit", "2", "--pooled", "2"])
    reward_crosscheck.main()
    printed = capsys.readouterr().out
    row = next(line for line in printed.splitlines() if line.startswith("PEBBLE/eps0.3/s0  | "))
    assert row.split("|")[1].split()[1].startswith("(")  # the refit's rank beside the model's
    assert "\na fresh model on the labels of 1 runs (PEBBLE; " in printed


def test_what_it_cannot_judge_is_refused_with_the_reason(runs, tmp_path, monkeypatch):
    (pebble_dir, _), _ = runs
    monkeypatch.setattr(sys, "argv", ["reward_crosscheck.py", str(pebble_dir),
                                      "--episodes", "1"])
    with pytest.raises(SystemExit):
        reward_crosscheck.main()
    monkeypatch.setattr(sys, "argv", ["reward_crosscheck.py", str(pebble_dir), "--episodes",
                                      "2", "--segment", "500"])
    with pytest.raises(SystemExit, match="an episode is shorter than --segment 500"):
        reward_crosscheck.main()
    with pytest.raises(SystemExit, match="no checkpoint.pt"):
        reward_crosscheck.load(str(tmp_path), episodes=2, seed=0, threads=1)


def test_a_refit_trains_a_fresh_model_on_the_runs_own_labels(runs, monkeypatch):
    (pebble_dir, _), (sac_dir, _) = runs
    played = [reward_crosscheck.refit(reward_crosscheck.load(str(d), episodes=2, seed=0,
                                                             threads=1), seed=3)
              for d in (pebble_dir, sac_dir)]
    refitted, model = played[0].refitted, played[0].model
    assert refitted is not None and model is not None and played[1].refitted is None

    with torch.random.fork_rng():  # the same initial weights, untrained
        torch.manual_seed(3)
        untrained = RewardModel(17, 6, refitted.cfg, torch.device("cpu"), 3)
    again = reward_crosscheck.refit(played[0], seed=3).refitted
    for mine, fresh, same in zip(refitted.ensemble.parameters(), untrained.ensemble.parameters(),
                                 again.ensemble.parameters(), strict=True):
        assert not torch.equal(mine, fresh)  # it trained
        assert torch.equal(mine, same)  # seeded

    # Its rank of the run's own policy comes from its own scores, not the run's model's.
    monkeypatch.setattr(model, "reward", lambda obs, action: obs[:, 8])
    monkeypatch.setattr(refitted, "reward", lambda obs, action: -obs[:, 8])
    j = reward_crosscheck.judge(played, pairs=20, segment=20, seed=0)[0]
    assert {j.own_rank, j.refitted_rank} == {1, 2}


def test_a_pooled_model_trains_on_the_chosen_variants_labels(runs, monkeypatch, capsys):
    (pebble_dir, _), (sac_dir, _) = runs
    played = [reward_crosscheck.load(str(d), episodes=2, seed=0, threads=1)
              for d in (pebble_dir, sac_dir)]
    assert played[0].labels is not None and len(played[0].labels) > 0
    assert played[1].labels is None  # the oracle has none

    model, sources = reward_crosscheck.pooled_model(played, {"PEBBLE"}, seed=4)
    assert sources == [played[0]]
    with torch.random.fork_rng():  # the same initial weights, untrained
        torch.manual_seed(4)
        untrained = RewardModel(17, 6, model.cfg, torch.device("cpu"), 4)
    assert not all(torch.equal(a, b) for a, b in zip(
        model.ensemble.parameters(), untrained.ensemble.parameters(), strict=True))
    with pytest.raises(SystemExit, match="--pooled-from SURF: no such run has labels"):
        reward_crosscheck.pooled_model(played, {"SURF"}, seed=4)

    # Its ranks come from its own scores: minus the ninth observation here.
    monkeypatch.setattr(model, "reward", lambda obs, action: -obs[:, 8])
    judged = reward_crosscheck.judge(played, pairs=20, segment=20, seed=0)
    reward_crosscheck.print_pooled(played, judged, model, sources, 20, 20, 0)
    rows = capsys.readouterr().out.splitlines()[-2:]
    scores = [np.mean([-e.observations[:-1, 8].astype(np.float64).sum() for e in p.episodes])
              for p in played]
    pooled_ranks = {p.label: 1 + int(np.sum(np.array(scores) > s))
                    for p, s in zip(played, scores, strict=True)}
    for row in rows:
        label, rest = row.split("  | ", 1)
        assert int(rest.split()[1]) == pooled_ranks[label]
        assert rest.endswith("yes" if label.startswith("PEBBLE") else "no")

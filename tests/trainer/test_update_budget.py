"""Equal update budgets: every algorithm makes one SAC gradient update per update step, so arms
compared at equal environment steps train their agents equally often."""

from __future__ import annotations

import csv

import pytest

from runvocab.config import build_config
from trainer.loop import TrainingRun
from trainer.sac import SAC

STEPS, FIRST_ROUND, UPDATE_EVERY, RESET_UPDATES = 1200, 400, 4, 10


def _run(tmp_path, algo: str, monkeypatch, **overrides) -> tuple[dict, int, dict]:
    """A tiny run whose first round closes at step 400 whatever the algorithm (PEBBLE and SURF:
    200 random and 200 unsupervised steps; S-EPOA: two initial rollouts of 200 steps); the SAC
    gradient updates it made, counted at SAC.update itself; its last episodes.csv row."""
    calls = []
    update = SAC.update
    monkeypatch.setattr(SAC, "update", lambda sac, batch: calls.append(1) or update(sac, batch))
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": algo, "steps": STEPS, "threads": 1, "teacher.eps": 0.3,
        "update_every": UPDATE_EVERY, "reset_updates": RESET_UPDATES,
        "skill.pretrain_steps": 0, "skill.initial_rollouts": 2,
        "skill.estimator_hidden_dim": 32, "skill.estimator_steps": 20,
        "run_dir": str(tmp_path / algo)} | overrides)
    run = TrainingRun(cfg, progress=False)
    summary = run.train()
    with open(tmp_path / algo / "episodes.csv", newline="") as f:
        last = list(csv.DictReader(f))[-1]
    return summary, len(calls), last


def test_sepoa_surf_and_pebble_make_the_same_number_of_updates_over_one_schedule(
        tmp_path, monkeypatch):
    on_r_hat = (STEPS - FIRST_ROUND) // UPDATE_EVERY + RESET_UPDATES
    runs = {algo: _run(tmp_path, algo, monkeypatch) for algo in ("pebble", "surf", "sepoa")}
    for algo, (summary, gradient_updates, last) in runs.items():
        assert summary["rounds"] >= 2, algo
        # The counters are the updates made, and episodes.csv logs them.
        assert summary["updates"] == gradient_updates, algo
        assert (int(last["updates"]), int(last["reward_updates"])) == (
            summary["updates"], summary["reward_updates"]), algo
        # One update per update step on the learned reward, and the post-reset updates.
        assert summary["reward_updates"] == on_r_hat, algo
    # PEBBLE's and SURF's other updates are their unsupervised phase's (steps 200-400);
    # S-EPOA's pretrained policy waits for the first round instead.
    pebble, surf, sepoa = (runs[a][0] for a in ("pebble", "surf", "sepoa"))
    assert pebble["updates"] == surf["updates"] == on_r_hat + (FIRST_ROUND - 200) // UPDATE_EVERY
    assert sepoa["updates"] == on_r_hat


@pytest.mark.parametrize("task_skill_update", [True, False])
def test_sepoa_z_task_updates_share_its_one_update_per_step(tmp_path, monkeypatch,
                                                             task_skill_update):
    summary, gradient_updates, _ = _run(tmp_path, "sepoa", monkeypatch,
                                        **{"skill.task_skill_update": task_skill_update})
    assert gradient_updates == summary["reward_updates"] == (
        (STEPS - FIRST_ROUND) // UPDATE_EVERY + RESET_UPDATES)

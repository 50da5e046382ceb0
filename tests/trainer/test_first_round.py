"""The first round opens where `runvocab.first_round_step` says (the step the server shows an
operator before a run starts), for each kind of run."""

from __future__ import annotations

import csv
import os

import pytest

from runvocab.config import build_config
from runvocab.first_round import first_round_step
from trainer.loop import TrainingRun


def _first_round(cfg) -> int:
    TrainingRun(cfg, progress=False).train()
    with open(os.path.join(cfg.run_dir, "rounds.csv"), newline="") as f:
        return int(next(csv.DictReader(f))["step"])


@pytest.mark.parametrize("overrides", [
    {"algo": "pebble"},
    {"algo": "pebble", "seed_steps": 250, "unsup_steps": 0},  # ends inside an episode
    {"algo": "sepoa", "skill.pretrain_steps": 0, "skill.initial_rollouts": 3},
])
def test_the_first_round_opens_at_the_step_the_configuration_gives(tmp_path, overrides):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "steps": 800, "threads": 1, "update_every": 8, "run_dir": str(tmp_path / "run"),
        "skill.snapshot_dir": str(tmp_path / "snapshots")} | overrides)
    assert _first_round(cfg) == first_round_step(cfg)


def test_runs_that_never_ask_and_runs_that_ask_before_step_0_open_at_0():
    assert first_round_step(build_config("dmc:cheetah_run", "paper", {"algo": "sac"})) == 0
    authors = build_config("dmc:cheetah_run", "paper", {
        "algo": "sepoa", "skill.free_initial_rollouts": True})
    assert first_round_step(authors) == 0
    # The defaults: PEBBLE after 1 000 random and 9 000 unsupervised steps; S-EPOA after its 20
    # initial rollouts of 1 000 steps; Metaworld episodes are 500 steps.
    assert first_round_step(build_config("dmc:cheetah_run", "paper", {"algo": "pebble"})) == 10_000
    assert first_round_step(build_config("dmc:cheetah_run", "paper", {"algo": "sepoa"})) == 20_000
    assert first_round_step(build_config("metaworld:button-press", "paper",
                                         {"algo": "sepoa"})) == 10_000

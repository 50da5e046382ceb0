"""A round's reward training, saved as it goes: a run killed inside it goes on from the last saved
epoch, and ends with the model an uninterrupted run ends with, bit for bit."""

from __future__ import annotations

import copy
import csv
import os

import numpy as np
import pytest
import torch
from trajectory_helpers import random_pool

from labelqueue.models import LabelSource
from runvocab.answers import Answer
from runvocab.config import build_config
from trainer.feedback import GivenAnswer, LabelLog, PreferenceFeedback
from trainer.hooks import RunHooks
from trainer.loop import TrainingRun
from trainer.reward_model import RewardModel
from trainer.round_progress import ROUND_PROGRESS, RoundProgress, round_key
from trainer.teachers import make_teacher
from trainer.trajectories import TrajectoryPool

OBS, ACT, LENGTH, SEGMENT = 3, 2, 30, 10
EPOCHS = 6


class Killed(Exception):
    """The process dies here."""


def _feedback(log_dir, reward: dict) -> PreferenceFeedback:
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "teacher.eps": 0.1, "feedback.segment_length": SEGMENT,
        "feedback.per_round": 8, "feedback.first_round_selection": "uniform",
        "feedback.selection": "uniform", "reward.max_epochs": EPOCHS,
        "reward.stop_accuracy": 1.0,
    } | reward)
    torch.manual_seed(0)  # the members' initial weights
    model = RewardModel(OBS, ACT, cfg.reward, torch.device("cpu"), 0)
    teacher = make_teacher(cfg.teacher, 0, SEGMENT, LENGTH)
    return PreferenceFeedback(cfg.feedback, model, teacher, "scripted:noisy",
                              LabelLog(str(log_dir / "labels.jsonl")), np.random.default_rng(1))


def _pool() -> TrajectoryPool:
    return random_pool(8, LENGTH, OBS, ACT)


def _second_round_open(log_dir, reward: dict) -> PreferenceFeedback:
    fb = _feedback(log_dir, reward)
    pool = _pool()
    fb.open_round(pool, step=100)
    fb.finish_round(pool, fb.scripted_answers())
    fb.open_round(pool, step=200)
    return fb


def _params(fb: PreferenceFeedback) -> list[torch.Tensor]:
    return [p.detach().clone() for p in fb.model.ensemble.parameters()]


def _without_seconds(metrics: dict) -> dict:
    """The round's metrics but its time, nan written as a string (nan != nan)."""
    return {k: "nan" if v != v else v for k, v in metrics.items() if k != "reward_seconds"}


@pytest.mark.parametrize("reward", [
    {}, {"reward.surf": True, "reward.surf_crop_min": 7, "reward.surf_crop_max": 9,
         "reward.surf_threshold": 0.51},  # most pseudo-labels count
    {"reward.rime": True}],
                         ids=["plain", "surf", "rime"])
def test_a_round_killed_in_its_reward_training_goes_on_from_its_last_saved_epoch(tmp_path,
                                                                                 reward, capsys):
    (tmp_path / "reference").mkdir()
    (tmp_path / "cut").mkdir()
    reference = _second_round_open(tmp_path / "reference", reward)
    expected = reference.finish_round(_pool(), reference.scripted_answers())
    assert expected["reward_epochs"] == EPOCHS  # the round runs every epoch

    cut = _second_round_open(tmp_path / "cut", reward)
    at_open = copy.deepcopy(cut.state_dict())  # what the run's checkpoint holds
    answers = cut.scripted_answers()
    heard: list[int] = []

    def die_in_third_epoch() -> None:
        heard.append(1)
        if len(heard) == 3:
            raise Killed

    progress = RoundProgress(str(tmp_path / "cut" / ROUND_PROGRESS), every_seconds=0)
    with pytest.raises(Killed):
        cut.finish_round(_pool(), answers, die_in_third_epoch, progress)

    resumed = _feedback(tmp_path / "cut", reward)
    resumed.load_state_dict(at_open)
    heard.clear()
    metrics = resumed.finish_round(_pool(), answers, lambda: heard.append(1), progress)
    assert len(heard) == EPOCHS - 2  # epochs 1 and 2 were saved; the third is trained again
    assert (f"round 1: reward training goes on from epoch 2 of {EPOCHS} ({progress.path})"
            in capsys.readouterr().err)
    assert _without_seconds(metrics) == _without_seconds(expected)
    for got, want in zip(_params(resumed), _params(reference), strict=True):
        assert torch.equal(got, want)
    assert metrics["reward_seconds"] > 0
    if "reward.surf" in reward:
        assert metrics["surf_confident_ratio"] > 0.5  # the unlabelled pairs' stream matters


def test_progress_saved_for_other_labels_is_not_used(tmp_path):
    fb = _second_round_open(tmp_path, {})
    at_open = copy.deepcopy(fb.state_dict())
    answers = fb.scripted_answers()
    progress = RoundProgress(str(tmp_path / ROUND_PROGRESS), every_seconds=0)

    def die_in_second_epoch(heard=[]) -> None:  # noqa: B006 (counts this round's epochs)
        heard.append(1)
        if len(heard) == 2:
            raise Killed

    with pytest.raises(Killed):
        fb.finish_round(_pool(), answers, die_in_second_epoch, progress)

    # After the restart someone else answered the first query, the other way.
    first = next(iter(answers))
    flipped = {"first": "second", "second": "first"}.get(str(answers[first].choice), "first")
    other = answers | {first: GivenAnswer(Answer(flipped), "crowd", LabelSource.HUMAN, 0.0)}
    resumed = _feedback(tmp_path, {})
    resumed.load_state_dict(at_open)
    heard: list[int] = []
    resumed.finish_round(_pool(), other, lambda: heard.append(1), progress)
    assert len(heard) == EPOCHS  # trained from the start


def test_the_round_key_tells_inputs_apart_by_value_shape_and_type():
    a = np.zeros((2, 3), np.float32)
    assert round_key([1, a]) == round_key([1, a.copy()])
    assert round_key([1, a]) != round_key([2, a])
    assert round_key([a]) != round_key([a.reshape(3, 2)])
    assert round_key([a]) != round_key([a.astype(np.float64)])
    assert round_key([[1, 2], None]) != round_key([[1, 2], 7])


def test_a_progress_file_answers_only_for_its_own_round(tmp_path):
    progress = RoundProgress(str(tmp_path / ROUND_PROGRESS), every_seconds=3600)
    assert progress.load("k") is None and not progress.due()
    progress.save("k", {"epochs": np.arange(3)})
    assert progress.load("other") is None
    assert np.array_equal(progress.load("k")["epochs"], np.arange(3))
    progress.clear()
    assert progress.load("k") is None
    progress.clear()  # nothing left to clear: no error


def _rounds(run_dir: str) -> list[dict]:
    with open(os.path.join(run_dir, "rounds.csv"), newline="") as f:
        return list(csv.DictReader(f))


def test_a_run_killed_inside_a_rounds_reward_training_resumes_from_its_saved_epochs(tmp_path):
    """The loop end to end: SURF, killed in the third epoch of its second round; the resumed run
    trains only that round's remaining epochs, leaves no progress file, and its rounds, labels
    and agent match an uninterrupted run's."""

    class Hooks(RunHooks):
        def __init__(self, kill: bool) -> None:
            self.kill, self.rounds, self.epochs = kill, 0, 0

        def metrics(self, stream, row):
            self.rounds += stream == "rounds"

        def reward_epoch(self, step):
            self.epochs += 1
            if self.kill and self.rounds == 1 and self.epochs == 3 + EPOCHS:
                raise Killed

    overrides = {"algo": "surf", "steps": 1300, "threads": 1, "feedback.budget": 20,
                 "reward.max_epochs": EPOCHS, "reward.stop_accuracy": 1.0}
    reference_cfg = build_config("dmc:cheetah_run", "tiny",
                                 overrides | {"run_dir": str(tmp_path / "reference")})
    reference = TrainingRun(reference_cfg, progress=False)
    expected = reference.train()

    cfg = build_config("dmc:cheetah_run", "tiny", overrides | {"run_dir": str(tmp_path / "cut")})
    first = Hooks(kill=True)
    run = TrainingRun(cfg, progress=False, hooks=first)
    run.round_progress.every_seconds = 0
    with pytest.raises(Killed):
        run.train()
    assert os.path.exists(os.path.join(cfg.run_dir, ROUND_PROGRESS))

    again = Hooks(kill=False)
    resumed = TrainingRun(cfg, resume=True, progress=False, hooks=again)
    summary = resumed.train()
    assert again.epochs == EPOCHS - 2  # the rest of round 1; there is no third round
    assert not os.path.exists(os.path.join(cfg.run_dir, ROUND_PROGRESS))
    keys = ("step", "labels_used", "reward_loss", "reward_accuracy", "reward_epochs",
            "surf_confident_ratio", "reward_corr")
    assert [{k: r[k] for k in keys} for r in _rounds(cfg.run_dir)] == [
        {k: r[k] for k in keys} for r in _rounds(reference_cfg.run_dir)]
    assert summary["mean_return_last10"] == expected["mean_return_last10"]
    for got, want in zip(resumed.agent.actor.parameters(), reference.agent.actor.parameters(),
                         strict=True):
        assert torch.equal(got, want)

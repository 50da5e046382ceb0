"""A run's feedback rounds at tiny sizes: how the budget pays for answers, what a scripted
answer is, and the SAC oracle's feedback, which never opens a round."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch
from trajectory_helpers import random_pool

from labelqueue.models import LabelSource
from runvocab.answers import Answer
from runvocab.config import build_config
from trainer.checkpoint import load_checkpoint
from trainer.feedback import GivenAnswer, LabelLog, NoFeedback, PreferenceFeedback
from trainer.hooks import RunHooks
from trainer.loop import TrainingRun
from trainer.reward_model import RewardModel
from trainer.teachers import make_teacher
from trainer.trajectories import TrajectoryPool

OBS, ACT, LENGTH, SEGMENT = 3, 2, 30, 10


def _feedback(tmp_path, **overrides) -> PreferenceFeedback:
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "teacher.eps": 0.0, "feedback.segment_length": SEGMENT,
        "feedback.first_round_selection": "uniform", "feedback.selection": "uniform",
    } | overrides)
    model = RewardModel(OBS, ACT, cfg.reward, torch.device("cpu"), 0)
    teacher = make_teacher(cfg.teacher, 0, SEGMENT, LENGTH)
    return PreferenceFeedback(cfg.feedback, model, teacher, "scripted:noisy",
                              LabelLog(str(tmp_path / "labels.jsonl")),
                              np.random.default_rng(1))


def _pool(n: int = 6) -> TrajectoryPool:
    return random_pool(n, LENGTH, OBS, ACT)


def _answers(queries, answers_each: int) -> dict[str, GivenAnswer]:
    """Every query answered by its shadow choice, standing for `answers_each` people."""
    return {q.query_id: GivenAnswer(Answer(q.shadow_choice), "crowd", LabelSource.HUMAN, 0.0,
                                    answers_each)
            for q in queries}


def test_answers_are_paid_per_person_and_a_round_asks_only_what_the_budget_can_pay(tmp_path):
    fb = _feedback(tmp_path, **{"feedback.budget": 9, "feedback.per_round": 3,
                                "feedback.labels_per_query": 2})
    pool = _pool()
    assert fb.budget_left == 8  # whole queries of 2 answers each

    first = fb.open_round(pool, step=100)
    assert len(first) == 3
    answers = _answers(first[:2], answers_each=2)  # the third query got no answer
    metrics = fb.finish_round(pool, answers)
    assert (metrics["queries"], metrics["answered"], metrics["answers"]) == (3, 2, 4)
    assert fb.labels_used == 4 and fb.budget_left == 4 and fb.rounds == 1

    second = fb.open_round(pool, step=200)
    assert len(second) == 2  # 5 answers left pay for two queries of 2, not per_round's 3
    fb.finish_round(pool, _answers(second, answers_each=2))
    assert fb.labels_used == 8 and fb.budget_left == 0
    assert fb.summary() == {"labels_used": 8, "rounds": 2}
    labelled = [json.loads(line)["query_id"] for line in open(tmp_path / "labels.jsonl")]
    assert labelled == ["r0-q0", "r0-q1", "r1-q0", "r1-q1"]


def test_scripted_answers_are_the_shadow_answers_and_cost_one_each(tmp_path):
    fb = _feedback(tmp_path, **{"feedback.budget": 30, "feedback.per_round": 4})
    pool = _pool()
    queries = fb.open_round(pool, step=50)
    scripted = fb.scripted_answers()
    assert {k: (str(a.choice), a.source, a.labeller) for k, a in scripted.items()} == {
        q.query_id: (q.shadow_choice, "scripted", "scripted:noisy") for q in queries}
    metrics = fb.finish_round(pool, scripted)
    assert fb.labels_used == 4 and metrics["shadow_agreement"] == 1.0
    # eps 0: the teacher prefers the segment with the larger true return.
    rows = [json.loads(line) for line in open(tmp_path / "labels.jsonl")]
    assert all(r["correct"] for r in rows if r["distinguishable"])
    assert fb.pending == []


def test_answers_to_queries_of_no_open_round_are_refused(tmp_path):
    fb = _feedback(tmp_path)
    pool = _pool()
    queries = fb.open_round(pool, step=0)
    stray = dataclasses.replace(queries[0], query_id="r7-q0")
    with pytest.raises(ValueError, match="r7-q0"):
        fb.finish_round(pool, _answers([stray], answers_each=1))


def test_a_round_closed_after_a_restore_logs_no_label_twice(tmp_path):
    fb = _feedback(tmp_path, **{"feedback.per_round": 3})
    pool = _pool()
    fb.open_round(pool, step=10)
    saved = fb.state_dict()
    fb.finish_round(pool, fb.scripted_answers())
    restored = _feedback(tmp_path, **{"feedback.per_round": 3})
    restored.load_state_dict(saved)
    restored.finish_round(pool, restored.scripted_answers())
    assert restored.labels_used == fb.labels_used == 3
    assert len(open(tmp_path / "labels.jsonl").readlines()) == 3


class _StopAt(RunHooks):
    def __init__(self, step: int):
        self.step = step

    def stop_requested(self, step: int) -> bool:
        return step >= self.step


def test_the_oracles_run_opens_no_round_and_resumes_from_a_checkpoint_without_feedback(
        tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sac", "steps": 600, "threads": 1, "run_dir": str(tmp_path)})
    run = TrainingRun(cfg, progress=False, hooks=_StopAt(200))
    assert isinstance(run.feedback, NoFeedback)
    assert run.train()["stopped"] == 1
    assert "feedback" not in load_checkpoint(str(tmp_path / "checkpoint.pt"))
    summary = TrainingRun(cfg, resume=True, progress=False).train()
    assert summary["step"] == 600 and "rounds" not in summary
    with open(tmp_path / "episodes.csv", newline="") as f:
        assert [row["labels_used"] for row in csv.DictReader(f)] == ["0"] * 3
    assert not (tmp_path / "labels.jsonl").exists() and not (tmp_path / "rounds.csv").exists()

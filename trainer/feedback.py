"""Feedback rounds: choose queries, ask the teacher, record every label, train the reward model.

Every answer becomes one JSON line in the run's `labels.jsonl`, written and flushed as soon as
it exists; that file is the record of truth for labels. A round is split in two so that a run
killed in the middle of one loses nothing: `open_round` selects the queries (the loop
checkpoints right after), `finish_round` asks only for the answers the label log lacks.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from trainer.config import FeedbackConfig
from trainer.query_selection import select_queries
from trainer.reward_model import LabelledPairs, RewardModel
from trainer.teachers import Choice, QueryTruth, choice_target
from trainer.trajectories import Trajectory, TrajectoryPool


@dataclass(frozen=True)
class Query:
    """One segment pair put to the teacher, with its provenance and hidden ground truth."""

    query_id: str
    round: int
    step: int
    trajectory0: int
    start0: int
    trajectory1: int
    start1: int
    segment_length: int
    segment_return0: float
    segment_return1: float
    trajectory_return0: float
    trajectory_return1: float
    model_p: float
    """the reward model's mean P[segment 1 preferred] at selection time"""
    score: float
    """the selection score (nan for uniform)"""
    rule: str


@dataclass(frozen=True)
class Label:
    query: Query
    choice: Choice
    distinguishable: bool
    correct: bool | None
    labeller: str
    source: str
    """scripted | human | gold"""
    answered_at: float


class LabelLog:
    """Append-only JSONL record of every label of a run."""

    def __init__(self, path: str):
        self.path = path

    def append(self, labels: list[Label]) -> None:
        with open(self.path, "a") as f:
            for label in labels:
                # Strict JSON: NaN (no model probability for uniform picks) becomes null.
                query = {k: None if isinstance(v, float) and v != v else v
                         for k, v in asdict(label.query).items()}
                row = query | {
                    "choice": str(label.choice),
                    "distinguishable": label.distinguishable,
                    "correct": label.correct,
                    "labeller": label.labeller,
                    "source": label.source,
                    "answered_at": label.answered_at,
                }
                f.write(json.dumps(row, allow_nan=False) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def read(self) -> list[dict]:
        if not os.path.exists(self.path):
            return []
        with open(self.path) as f:
            return [json.loads(line) for line in f if line.strip()]


def _segment(traj: Trajectory, start: int, length: int) -> np.ndarray:
    end = start + length
    return np.concatenate([traj.obs[start:end], traj.actions[start:end]], axis=1)


class PreferenceFeedback:
    """Owns the labelled pairs, the budget and the round counter of one run."""

    def __init__(self, cfg: FeedbackConfig, reward_model: RewardModel, teacher, labeller: str,
                 label_log: LabelLog, rng: np.random.Generator):
        self.cfg, self.model, self.teacher = cfg, reward_model, teacher
        self.labeller, self.log, self.rng = labeller, label_log, rng
        self.pairs = LabelledPairs()
        self.labels_used = 0
        self.rounds = 0
        self.pending: list[Query] = []

    @property
    def budget_left(self) -> int:
        return self.cfg.budget - self.labels_used

    def open_round(self, pool: TrajectoryPool, step: int) -> list[Query]:
        """Select this round's queries; they stay pending until `finish_round`."""
        n = min(self.cfg.per_round, self.budget_left)
        rule = self.cfg.first_round_selection if self.rounds == 0 else self.cfg.selection
        trajectories = list(pool.trajectories)
        selection = select_queries(
            rule, self.model, trajectories, n, n * self.cfg.candidate_factor,
            self.cfg.segment_length, self.rng,
        )
        q, h = selection.queries, self.cfg.segment_length
        queries = []
        for i in range(len(q)):
            t0, t1 = trajectories[q.traj0[i]], trajectories[q.traj1[i]]
            s0, s1 = int(q.start0[i]), int(q.start1[i])
            queries.append(Query(
                query_id=f"r{self.rounds}-q{i}", round=self.rounds, step=step,
                trajectory0=t0.id, start0=s0, trajectory1=t1.id, start1=s1, segment_length=h,
                segment_return0=float(t0.true_rewards[s0 : s0 + h].sum(dtype=np.float64)),
                segment_return1=float(t1.true_rewards[s1 : s1 + h].sum(dtype=np.float64)),
                trajectory_return0=t0.true_return, trajectory_return1=t1.true_return,
                model_p=float(selection.probability[i]), score=float(selection.score[i]),
                rule=rule,
            ))
        self.pending = queries
        return queries

    def finish_round(self, pool: TrajectoryPool) -> dict[str, float]:
        """Collect the answers to the pending queries (those already in the label log are
        reused, not asked again), then train the reward model on every label so far."""
        queries, by_id = self.pending, {t.id: t for t in pool.trajectories}
        logged = {row["query_id"]: row for row in self.log.read() if row["round"] == self.rounds}
        for q in queries:
            row = logged.get(q.query_id)
            if row and (row["trajectory0"], row["start0"], row["trajectory1"], row["start1"]) != (
                    q.trajectory0, q.start0, q.trajectory1, q.start1):
                raise RuntimeError(f"labels.jsonl holds a different query under {q.query_id}")
        # The teacher answers every query so its random stream advances as in an uninterrupted
        # run; answers already on record win. It takes R_avg from the latest returns.
        answers = self.teacher.answer([self._truth(q, by_id) for q in queries], pool.returns)
        now = time.time()
        new = [
            Label(q, a.choice, a.distinguishable, a.correct, self.labeller, "scripted", now)
            for q, a in zip(queries, answers, strict=True)
            if q.query_id not in logged
        ]
        self.log.append(new)
        answered = {lab.query.query_id: (str(lab.choice), lab.distinguishable, lab.correct)
                    for lab in new}
        for qid, row in logged.items():
            answered[qid] = (row["choice"], row["distinguishable"], row["correct"])

        for q in queries:
            target = choice_target(Choice(answered[q.query_id][0]))
            if target is not None:
                self.pairs.add(
                    _segment(by_id[q.trajectory0], q.start0, q.segment_length),
                    _segment(by_id[q.trajectory1], q.start1, q.segment_length),
                    target,
                )
        self.labels_used += len(queries)
        results = [answered[q.query_id] for q in queries]
        metrics = {
            "round": self.rounds,
            "queries": len(queries),
            "labels_used": self.labels_used,
            "distinguishable_ratio": float(np.mean([r[1] for r in results])) if results else 0.0,
            "teacher_accuracy": _mean([r[2] for r in results if r[2] is not None]),
            "trained_pairs": len(self.pairs),
        }
        if len(self.pairs):
            metrics |= self.model.train_round(self.pairs)
        self.rounds += 1
        self.pending = []
        return metrics

    @staticmethod
    def _truth(q: Query, by_id: dict[int, Trajectory]) -> QueryTruth:
        t0, t1, h = by_id[q.trajectory0], by_id[q.trajectory1], q.segment_length
        return QueryTruth(
            segment_rewards0=t0.true_rewards[q.start0 : q.start0 + h],
            segment_rewards1=t1.true_rewards[q.start1 : q.start1 + h],
            trajectory_return0=t0.true_return,
            trajectory_return1=t1.true_return,
        )

    def state_dict(self) -> dict:
        return {
            "pairs": self.pairs.state_dict(),
            "labels_used": self.labels_used,
            "rounds": self.rounds,
            "pending": [asdict(q) for q in self.pending],
            "rng": self.rng.bit_generator.state,
            "teacher": self.teacher.state_dict(),
            "model": self.model.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.pairs.load_state_dict(state["pairs"])
        self.labels_used, self.rounds = state["labels_used"], state["rounds"]
        self.pending = [Query(**q) for q in state["pending"]]
        self.rng.bit_generator.state = state["rng"]
        self.teacher.load_state_dict(state["teacher"])
        self.model.load_state_dict(state["model"])


def _mean(values: list) -> float:
    return float(np.mean(values)) if values else float("nan")

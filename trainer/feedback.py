"""Feedback rounds: choose queries, gather answers, record every label, train the reward model.

A round is split in two so that a run killed in the middle of one loses nothing: `open_round`
selects the queries and has the run's scripted teacher answer them at once (its *shadow*
answers, kept with the queries and checkpointed by the loop right after); `finish_round` takes
the answers that count, from whoever gave them, and trains. Standalone runs answer with the
shadow answers themselves (`scripted_answers`); a worker takes them from the queue database,
where people or the scripted teacher put them.

Every answer becomes one JSON line in the run's `labels.jsonl`, flushed as soon as it exists;
a round finished again after a resume adds no second line for a query.

The budget counts answers, as the queue's `runs.labels_used` does: a query that
`labels_per_query` (k) people answer costs k, one the scripted teacher answers costs 1, and gold
pairs cost nothing (they are not the trainer's). A round asks for no more queries than the
budget can still pay k answers for each, so the queue never takes more answers than the budget.
"""

from __future__ import annotations

import copy
import json
import os
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from labelqueue.models import LabelSource
from runvocab.answers import Answer
from runvocab.config import FeedbackConfig
from trainer.query_selection import (
    Candidates,
    PoolRewards,
    pool_rewards,
    sample_candidates,
    select_queries,
)
from trainer.replay_buffer import ReplayBuffer
from trainer.return_estimator import ReplayEpisodes, ReturnEstimator
from trainer.reward_model import LabelledPairs, RewardModel, TrainingProgress
from trainer.round_progress import RoundLeft, RoundProgress, round_key
from trainer.teachers import (
    BPrefTeacher,
    NoisyTeacher,
    QueryTruth,
    choice_target,
    is_correct,
    recent_mean,
)
from trainer.trajectories import Trajectory, TrajectoryPool, stacked_skills
from trainer.true_reward_rounds import TrueRewardRounds


@dataclass(frozen=True)
class Query:
    """One segment pair put to the teacher, with its provenance and hidden ground truth.

    The attributes the queue stores are declared in `runvocab.query_fields` (each field's
    `trainer` names its attribute here); a new one needs a default, so older checkpoints load.
    """

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
    shadow_choice: str
    """the run's scripted teacher's answer, given when the round opened"""
    distinguishable: bool
    """whether the scripted teacher could tell the pair apart"""
    r_avg: float = float("nan")
    """R_avg when the round opened: the mean of the teacher's recent trajectory returns, the
    scale of the noisy teacher's band (nan in checkpoints from before it was recorded)"""


@dataclass(frozen=True)
class GivenAnswer:
    """An answer to a query, from a person or a scripted teacher."""

    choice: Answer
    labeller: str
    source: LabelSource
    """who answered: a person, or a scripted teacher"""
    answered_at: float
    answers: int = 1
    """the answers this one stands for, each paid from the budget: the labels its query got
    (up to `labels_per_query` people's, or the scripted teacher's one)"""


@dataclass(frozen=True)
class Label:
    query: Query
    choice: Answer
    distinguishable: bool
    correct: bool | None
    labeller: str
    source: LabelSource
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
    """Owns the labelled pairs, the budget (in answers) and the round counter of one run."""

    def __init__(self, cfg: FeedbackConfig, reward_model: RewardModel,
                 teacher: NoisyTeacher | BPrefTeacher, labeller: str,
                 label_log: LabelLog, rng: np.random.Generator,
                 estimator: ReturnEstimator | None = None, spread: str = "var",
                 replay: ReplayEpisodes | None = None, refit_estimator: bool = True):
        self.cfg, self.model, self.teacher = cfg, reward_model, teacher
        self.labeller, self.log, self.rng = labeller, label_log, rng
        self.estimator, self.spread = estimator, spread
        """S-EPOA's R_theta(z) (skill rule only), refitted as each round selects"""
        self.refit_estimator = refit_estimator
        """R_theta fitted again after each round's reward training (`skill.estimator_refit`)"""
        self.replay = replay
        """R_theta's data where it is every replay episode (`skill.estimator_data`); None: the
        pool's trajectories"""
        self.pairs = LabelledPairs()
        self.labels_used = 0
        """answers paid for so far (the queue's `runs.labels_used` once the round closed)"""
        self.rounds = 0
        self.pending: list[Query] = []
        self.compare_ratio = float("nan")
        """the open round's `cfg.compare_rule` diagnostic (nan when off)"""

    @property
    def budget_left(self) -> int:
        """The answers the budget can still pay for, in whole queries of `labels_per_query`
        answers each: 0 once fewer are left than one query asks for (feedback is over)."""
        k = self.cfg.labels_per_query
        return max(0, self.cfg.budget - self.labels_used) // k * k

    def open_round(self, pool: TrajectoryPool, step: int) -> list[Query]:
        """Select this round's queries, as many as the budget can pay `labels_per_query`
        answers each (at most `per_round`); they stay pending until `finish_round`."""
        n = min(self.cfg.per_round, self.budget_left // self.cfg.labels_per_query)
        rule = self.cfg.first_round_selection if self.rounds == 0 else self.cfg.selection
        trajectories = list(pool.trajectories)
        compare = bool(self.cfg.compare_rule) and rule != "uniform"
        rewards = None
        if rule == "skill" or compare:  # the pool scored once, for every use below
            rewards = pool_rewards(self.model, trajectories)
        if rule == "skill":  # R_theta on the trajectories that came since the last round too
            self.fit_estimator(pool, rewards)
        selection = select_queries(
            rule, self.model, trajectories, n, self.cfg.candidate_factor,
            self.cfg.segment_length, self.rng, self.estimator, self.spread, rewards,
            self.cfg.selection_mode,
        )
        h = self.cfg.segment_length
        self.compare_ratio = float("nan")
        if compare:
            assert rewards is not None  # scored above for the comparison
            self.compare_ratio = self._compare(pool, n, rewards)
        pairs = _pairs(trajectories, selection.queries)
        # The teacher answers now, once per query, whoever ends up answering: its random stream
        # then depends only on the queries, and it takes R_avg from the latest returns.
        shadow = self.teacher.answer([_truth(t0, s0, t1, s1, h) for t0, s0, t1, s1 in pairs],
                                     pool.returns)
        r_avg = recent_mean(pool.returns, self.teacher.recent_trajectories)
        queries = []
        for i, ((t0, s0, t1, s1), answer) in enumerate(zip(pairs, shadow, strict=True)):
            queries.append(Query(
                query_id=f"r{self.rounds}-q{i}", round=self.rounds, step=step,
                trajectory0=t0.id, start0=s0, trajectory1=t1.id, start1=s1, segment_length=h,
                segment_return0=float(t0.true_rewards[s0 : s0 + h].sum(dtype=np.float64)),
                segment_return1=float(t1.true_rewards[s1 : s1 + h].sum(dtype=np.float64)),
                trajectory_return0=t0.true_return, trajectory_return1=t1.true_return,
                model_p=float(selection.probability[i]), score=float(selection.score[i]),
                rule=rule, shadow_choice=str(answer.choice),
                distinguishable=answer.distinguishable, r_avg=r_avg,
            ))
        self.pending = queries
        return queries

    def _compare(self, pool: TrajectoryPool, n: int, rewards: PoolRewards) -> float:
        """The share of `cfg.compare_rule`'s picks on this pool and model that the teacher
        could tell apart. Its own random streams (a generator seeded by the round, a copy of
        the teacher): the run's selection and answers are the same with or without it."""
        trajectories, h = list(pool.trajectories), self.cfg.segment_length
        rng = np.random.default_rng([self.rounds, 0x5E1EC7])
        other = select_queries(
            self.cfg.compare_rule, self.model, trajectories, n, self.cfg.candidate_factor, h,
            rng, self.estimator, self.spread, rewards, self.cfg.selection_mode,
        )
        truths = [_truth(t0, s0, t1, s1, h) for t0, s0, t1, s1 in _pairs(trajectories,
                                                                           other.queries)]
        answers = copy.deepcopy(self.teacher).answer(truths, pool.returns)
        return _mean([a.distinguishable for a in answers])

    def fit_estimator(self, pool: TrajectoryPool,
                      rewards: PoolRewards | None = None) -> dict[str, float]:
        """S-EPOA: refit R_theta on the pool's skills and summed predicted rewards (`rewards`:
        the pool already scored by the current model), or on every replay episode's."""
        assert self.estimator is not None
        if self.replay is not None:
            return self.estimator.fit(*self.replay.skills_and_returns(self.model.reward))
        trajectories = list(pool.trajectories)
        if rewards is None:
            rewards = pool_rewards(self.model, trajectories)
        returns = rewards.trajectory_returns()
        return self.estimator.fit(stacked_skills(trajectories), returns)

    def scripted_answers(self) -> dict[str, GivenAnswer]:
        """The shadow answers of the open round, as the answers of a standalone run."""
        now = time.time()
        return {q.query_id: GivenAnswer(Answer(q.shadow_choice), self.labeller,
                                        LabelSource.SCRIPTED, now)
                for q in self.pending}

    def finish_round(self, pool: TrajectoryPool, answers: Mapping[str, GivenAnswer],
                     after_epoch: Callable[[], bool | None] | None = None,
                     progress: RoundProgress | None = None) -> dict[str, float]:
        """Close the open round with `answers` (by query id; a query without one is dropped and
        costs no budget; one with an answer costs the answers it stands for), log the new ones,
        and train the reward model on every label so far (saving its training as it goes to
        `progress`, and going on from what that holds for this round)."""
        queries, by_id = self.pending, {t.id: t for t in pool.trajectories}
        unknown = set(answers) - {q.query_id for q in queries}
        if unknown:
            raise ValueError(f"answers for queries not in round {self.rounds}: {sorted(unknown)}")
        logged = {row["query_id"]: row for row in self.log.read() if row["round"] == self.rounds}
        for q in queries:
            row = logged.get(q.query_id)
            if row and (row["trajectory0"], row["start0"], row["trajectory1"], row["start1"]) != (
                    q.trajectory0, q.start0, q.trajectory1, q.start1):
                raise RuntimeError(f"labels.jsonl holds a different query under {q.query_id}")

        answered = [(q, answers[q.query_id]) for q in queries if q.query_id in answers]
        labels = [
            Label(q, a.choice, q.distinguishable, is_correct(a.choice, _query_truth(q, by_id)),
                  a.labeller, a.source, a.answered_at)
            for q, a in answered
        ]
        self.log.append([lab for lab in labels if lab.query.query_id not in logged])

        for q, a in answered:
            target = choice_target(a.choice)
            if target is not None:
                self.pairs.add(
                    _segment(by_id[q.trajectory0], q.start0, q.segment_length),
                    _segment(by_id[q.trajectory1], q.start1, q.segment_length),
                    target,
                )
        spent = sum(a.answers for _, a in answered)
        self.labels_used += spent
        metrics = {
            "round": self.rounds,
            "queries": len(queries),
            "answered": len(answered),
            "answers": spent,
            "labels_used": self.labels_used,
            # Of the selected pairs, whether or not anyone answered: the paper's ratio.
            "distinguishable_ratio": _mean([q.distinguishable for q in queries]),
            "teacher_accuracy": _mean([lab.correct for lab in labels if lab.correct is not None]),
            "shadow_agreement": _agreement(
                [(str(a.choice), q.shadow_choice) for q, a in answered]),
            "model_agreement": _agreement(
                [(_model_choice(q.model_p), q.shadow_choice) for q in queries]),
            "trained_pairs": len(self.pairs),
        } | _spread_over_trajectories(queries)
        if self.cfg.compare_rule:
            metrics["compare_distinguishable_ratio"] = self.compare_ratio
        if len(self.pairs):
            metrics |= self._train(pool, after_epoch, progress)
        if self.estimator is not None and self.refit_estimator:  # z_task follows it at once
            start = time.perf_counter()
            metrics |= self.fit_estimator(pool)
            metrics["estimator_seconds"] = time.perf_counter() - start
        self.rounds += 1
        self.pending = []
        return metrics

    def _train(self, pool: TrajectoryPool, after_epoch: Callable[[], bool | None] | None,
               progress: RoundProgress | None) -> dict[str, float]:
        """Train the reward model on every label so far, going on from `progress` where it
        holds this round's training; `after_epoch` returning True leaves the round after saving
        (`RoundLeft`)."""
        start = time.perf_counter()
        unlabelled = None
        if self.model.cfg.surf:  # its stream is drawn from the run's once per round
            unlabelled = UnlabelledPairs(pool, self.cfg.segment_length,
                                         int(self.rng.integers(2**63)))
        key, resume, seconds_before = "", None, 0.0
        if progress is not None:
            key = self._round_key(pool, unlabelled)
            saved = progress.load(key)
            if saved is not None:
                self.model.load_state_dict(saved["model"])
                if unlabelled is not None:
                    unlabelled.rng.bit_generator.state = saved["unlabelled_rng"]
                resume = TrainingProgress(**saved["training"])
                seconds_before = saved["seconds"]
                print(f"round {self.rounds}: reward training goes on from epoch {resume.epochs} "
                      f"of {self.model.cfg.max_epochs} ({progress.path})", file=sys.stderr,
                      flush=True)
            progress.start()

        def epoch_done(p: TrainingProgress) -> None:
            leave = bool(after_epoch()) if after_epoch is not None else False
            if progress is None:
                return  # nowhere to keep the training: a run told to go finishes the round
            if p.finished or leave or progress.due():
                progress.save(key, {
                    "model": self.model.state_dict(), "training": p,
                    "seconds": seconds_before + time.perf_counter() - start,
                } | ({"unlabelled_rng": unlabelled.rng.bit_generator.state}
                     if unlabelled is not None else {}))
            if leave and not p.finished:
                raise RoundLeft(p.epochs)

        metrics = self.model.train_round(self.pairs, unlabelled, epoch_done, resume)
        # The round's training time, over the runs it took if a kill cut it.
        metrics["reward_seconds"] = seconds_before + time.perf_counter() - start
        return metrics

    def _round_key(self, pool: TrajectoryPool, unlabelled: UnlabelledPairs | None) -> str:
        """What this round's reward training depends on besides the model it starts from."""
        seg0, seg1 = (np.stack(s) for s in (self.pairs.seg0, self.pairs.seg1))
        return round_key([
            self.rounds, asdict(self.model.cfg), seg0, seg1,
            np.asarray(self.pairs.targets, np.float32),
            [t.id for t in pool.trajectories], unlabelled and unlabelled.seed,
        ])

    def relabel(self, buffer: ReplayBuffer) -> None:
        """Every stored transition trains on the current r_hat from now on."""
        buffer.relabel(self.model.reward)

    def summary(self) -> dict[str, int]:
        """What a run's summary reports of its feedback."""
        return {"labels_used": self.labels_used, "rounds": self.rounds}

    def state_dict(self) -> dict:
        return {
            "pairs": self.pairs.state_dict(),
            "labels_used": self.labels_used,
            "rounds": self.rounds,
            "pending": [asdict(q) for q in self.pending],
            "compare_ratio": self.compare_ratio,
            "rng": self.rng.bit_generator.state,
            "teacher": self.teacher.state_dict(),
            "model": self.model.state_dict(),
        } | ({"estimator": self.estimator.state_dict()} if self.estimator else {})

    def load_state_dict(self, state: dict) -> None:
        self.pairs.load_state_dict(state["pairs"])
        self.labels_used, self.rounds = state["labels_used"], state["rounds"]
        self.pending = [Query(**q) for q in state["pending"]]
        self.compare_ratio = state["compare_ratio"]
        self.rng.bit_generator.state = state["rng"]
        self.teacher.load_state_dict(state["teacher"])
        self.model.load_state_dict(state["model"])
        if self.estimator is not None:
            self.estimator.load_state_dict(state["estimator"])


class NoFeedback:
    """The SAC oracle's feedback: it trains on the true reward, so it has no reward model and
    asks no queries. Its budget is 0, so no round ever opens; it adds nothing to the run's
    summary, and nothing to its checkpoint."""

    labels_used = 0
    rounds = 0
    budget_left = 0

    @property
    def pending(self) -> list[Query]:
        return []

    def summary(self) -> dict[str, int]:
        return {}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """A SAC checkpoint holds no feedback: nothing to restore."""


Feedback = PreferenceFeedback | NoFeedback | TrueRewardRounds
"""a run's feedback: preference rounds, none (the SAC oracle), or rounds on the true reward
(a diagnostic, `reward.true_reward`)"""


class UnlabelledPairs:
    """SURF's unlabelled pairs: random segments of different pooled trajectories, from a stream
    of their own (seeded from the run's once per round, so that the selection's stream stays
    as without SURF)."""

    def __init__(self, pool: TrajectoryPool, segment_length: int, seed: int):
        self.trajectories, self.h, self.seed = list(pool.trajectories), segment_length, seed
        self.lengths = np.array([t.length for t in self.trajectories])
        self.rng = np.random.default_rng(seed)

    def __call__(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        c = sample_candidates(self.lengths, n, self.h, self.rng)
        seg0, seg1 = (
            np.stack([_segment(self.trajectories[i], s, self.h) for i, s in zip(t, st,
                                                                                  strict=True)])
            for t, st in ((c.traj0, c.start0), (c.traj1, c.start1)))
        return seg0, seg1


def _pairs(trajectories: list[Trajectory], q: Candidates) -> list[tuple[Trajectory, int,
                                                                        Trajectory, int]]:
    return [(trajectories[q.traj0[i]], int(q.start0[i]), trajectories[q.traj1[i]],
             int(q.start1[i])) for i in range(len(q))]


def _spread_over_trajectories(queries: list[Query]) -> dict[str, float]:
    """How a round's queries spread over the pool: distinct trajectory pairs, and the largest
    share of the queries that one trajectory took part in."""
    if not queries:
        return {"trajectory_pairs": 0, "max_trajectory_share": float("nan")}
    pairs = {tuple(sorted((q.trajectory0, q.trajectory1))) for q in queries}
    counts: dict[int, int] = {}
    for q in queries:
        for t in (q.trajectory0, q.trajectory1):
            counts[t] = counts.get(t, 0) + 1
    return {"trajectory_pairs": len(pairs),
            "max_trajectory_share": max(counts.values()) / len(queries)}


def _truth(t0: Trajectory, s0: int, t1: Trajectory, s1: int, h: int) -> QueryTruth:
    return QueryTruth(
        segment_rewards0=t0.true_rewards[s0 : s0 + h],
        segment_rewards1=t1.true_rewards[s1 : s1 + h],
        trajectory_return0=t0.true_return,
        trajectory_return1=t1.true_return,
    )


def _query_truth(q: Query, by_id: dict[int, Trajectory]) -> QueryTruth:
    return _truth(by_id[q.trajectory0], q.start0, by_id[q.trajectory1], q.start1,
                  q.segment_length)


def _model_choice(p: float) -> str | None:
    """The reward model's preference from its P[segment 1 preferred]; None without a model."""
    if p != p:
        return None
    return "second" if p > 0.5 else "first" if p < 0.5 else "equal"


def _agreement(pairs: list[tuple[str | None, str]]) -> float:
    """How often two answers agree, over the pairs where both state a preference."""
    preferences = ("first", "second", "equal")
    both = [(a, b) for a, b in pairs if a in preferences and b in preferences]
    return _mean([a == b for a, b in both])


def _mean(values: list) -> float:
    return float(np.mean(values)) if values else float("nan")

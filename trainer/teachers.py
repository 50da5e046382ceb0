"""Scripted teachers that answer preference queries from hidden ground-truth rewards.

Two families, both with the same `answer(truths, recent_returns)` call, so every method in a
comparison is labelled by the same teacher:

- `NoisyTeacher`: the paper's noisy scripted teacher. When the *whole trajectories* behind a
  query have nearly equal ground-truth returns (|R(tau0) - R(tau1)| < eps * |R_avg|) it answers
  at random; otherwise the segments' ground-truth sums decide. eps = 0 is the ideal teacher.
  Segments with exactly equal sums (a cheetah that does not move earns 0 in both) answer by
  `teacher.tie`: EQUAL by default, a deviation from the paper's one-hot labels.
- `BPrefTeacher`: B-Pref's simulated teacher (Lee et al. 2021) with its knobs: skip, equal,
  myopic discount gamma, Bradley-Terry rationality beta, and a mistake probability.

Both draw a fixed number of uniforms per query, used or not, so the random stream depends only
on the queries asked; `state_dict` / `load_state_dict` carry the generator for resumed runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from runvocab.answers import Answer
from runvocab.config import TeacherConfig
from runvocab.names import TEACHER_KINDS, TIES

# Training target: the probability that segment 1 is preferred.
_TARGETS: dict[Answer, float | None] = {
    Answer.FIRST: 0.0,
    Answer.SECOND: 1.0,
    Answer.EQUAL: 0.5,
    Answer.CANT_TELL: None,
    Answer.SKIP: None,
}


def choice_target(choice: Answer) -> float | None:
    """0.0 / 1.0 / 0.5 for FIRST / SECOND / EQUAL; None for answers that are not trained on."""
    return _TARGETS[Answer(choice)]


@dataclass(frozen=True)
class QueryTruth:
    """Hidden ground truth of one query; never shown to a human labeller."""

    segment_rewards0: np.ndarray
    """(H,) ground-truth per-step rewards of segment 0"""
    segment_rewards1: np.ndarray
    """(H,) ground-truth per-step rewards of segment 1"""
    trajectory_return0: float
    """ground-truth return of the whole trajectory segment 0 comes from"""
    trajectory_return1: float
    """ground-truth return of the whole trajectory segment 1 comes from"""


@dataclass(frozen=True)
class TeacherAnswer:
    choice: Answer
    distinguishable: bool
    """could the teacher tell the pair apart"""
    correct: bool | None
    """does a FIRST/SECOND choice agree with the segment-sum comparison (None otherwise or on a
    tie of the sums)"""


# ---------------------------------------------------------------------------------------------
# Shared helpers


def recent_mean(recent_returns: Sequence[float], n: int) -> float:
    """Mean of the last `n` returns (oldest first); 0 when there are none yet."""
    last = list(recent_returns)[-n:]
    return float(np.mean(last)) if last else 0.0


def _sum_choice(sum0: float, sum1: float, tie: str = "equal", u: float = 0.0) -> Answer:
    """The larger sum wins; an exact tie answers by `tie`: EQUAL, a coin (`u` a uniform), or
    FIRST (B-Pref's argmax)."""
    if sum1 > sum0:
        return Answer.SECOND
    if sum0 > sum1:
        return Answer.FIRST
    if tie == "random":
        return Answer.SECOND if u < 0.5 else Answer.FIRST
    return Answer.FIRST if tie == "first" else Answer.EQUAL


def is_correct(choice: Answer, truth: QueryTruth) -> bool | None:
    """Agreement of a FIRST/SECOND choice with the plain segment-sum comparison."""
    best = _sum_choice(float(np.sum(truth.segment_rewards0)), float(np.sum(truth.segment_rewards1)))
    if choice not in (Answer.FIRST, Answer.SECOND) or best is Answer.EQUAL:
        return None
    return choice is best


def _check_tie(tie: str) -> None:
    if tie not in TIES:
        raise ValueError(f"unknown teacher.tie {tie!r}; valid: {', '.join(TIES)}")


def _flip(choice: Answer) -> Answer:
    return {Answer.FIRST: Answer.SECOND, Answer.SECOND: Answer.FIRST}.get(choice, choice)


def _sigmoid(x: float) -> float:
    # Two branches so a large |x| neither overflows nor warns.
    if x >= 0:
        return 1.0 / (1.0 + math.exp(-x))
    z = math.exp(x)
    return z / (1.0 + z)


def _rng_state(rng: np.random.Generator, kind: str) -> dict:
    return {"kind": kind, "bit_generator": rng.bit_generator.state}


def _load_rng_state(rng: np.random.Generator, kind: str, d: dict) -> None:
    if d.get("kind") != kind:
        raise ValueError(f"teacher state is for kind {d.get('kind')!r}, not {kind!r}")
    rng.bit_generator.state = d["bit_generator"]


# ---------------------------------------------------------------------------------------------
# The paper's teacher


class NoisyTeacher:
    """Random FIRST/SECOND when the two trajectories' returns are within eps * |R_avg|.

    Unlike the authors' code, each indistinguishable pair gets its own fair coin (their code
    flips exactly floor(n/2) of a round's such pairs), and no method gets extra label flips.
    """

    kind = "noisy"

    def __init__(self, eps: float, seed: int,
                 recent_trajectories: int = TeacherConfig.recent_trajectories,
                 tie: str = TeacherConfig.tie):
        if not eps >= 0:
            raise ValueError(f"eps must be >= 0, got {eps}")
        if recent_trajectories < 1:
            raise ValueError(f"recent_trajectories must be >= 1, got {recent_trajectories}")
        _check_tie(tie)
        self.eps, self.tie = float(eps), tie
        self.recent_trajectories = recent_trajectories
        self.rng = np.random.default_rng(seed)

    def threshold(self, recent_returns: Sequence[float]) -> float:
        """eps * |R_avg|. The paper writes eps * R_avg; |.| keeps the band non-empty for tasks
        with negative returns. No finished trajectory yet -> R_avg = 0 -> empty band."""
        return self.eps * abs(recent_mean(recent_returns, self.recent_trajectories))

    def answer(
        self, truths: Sequence[QueryTruth], recent_returns: Sequence[float]
    ) -> list[TeacherAnswer]:
        thres = self.threshold(recent_returns)
        # One uniform per query, used or not, so the stream does not depend on the outcomes.
        coins = self.rng.random(len(truths))
        answers = []
        for truth, u in zip(truths, coins, strict=True):
            gap = abs(float(truth.trajectory_return0) - float(truth.trajectory_return1))
            if gap < thres:  # strict: eps = 0 is never random, the boundary is distinguishable
                choice = Answer.SECOND if u < 0.5 else Answer.FIRST
                distinguishable = False
            else:
                choice = _sum_choice(float(np.sum(truth.segment_rewards0)),
                                     float(np.sum(truth.segment_rewards1)), self.tie, u)
                distinguishable = True
            answers.append(TeacherAnswer(choice, distinguishable, is_correct(choice, truth)))
        return answers

    def state_dict(self) -> dict:
        return _rng_state(self.rng, self.kind)

    def load_state_dict(self, d: dict) -> None:
        _load_rng_state(self.rng, self.kind, d)


# ---------------------------------------------------------------------------------------------
# B-Pref's teacher family


def _myopic_sum(rewards: np.ndarray, gamma: float) -> float:
    """Sum with step t of H weighted gamma^(H-1-t): the last step counts fully."""
    r = np.asarray(rewards, dtype=np.float64).reshape(-1)
    weights = gamma ** np.arange(len(r) - 1, -1, -1, dtype=np.float64)
    return float(np.dot(weights, r))


class BPrefTeacher:
    """B-Pref's simulated teacher: skip -> equal -> (myopic, Bradley-Terry) choice -> mistake.

    As in B-Pref, skip and equal test the plain segment sums against thresholds scaled from the
    plain episode returns; gamma only shapes the choice itself. Exact ties under beta = inf
    answer by `teacher.tie` (default EQUAL; B-Pref silently picks the first segment). B-Pref
    also squares eps_mistake after the first round by mistake; here it stays constant.
    """

    kind = "bpref"

    def __init__(self, cfg: TeacherConfig, seed: int, segment_length: int, episode_length: int):
        if not cfg.beta >= 0:
            raise ValueError(f"beta must be >= 0 (inf = rational), got {cfg.beta}")
        if not 0.0 <= cfg.gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {cfg.gamma}")
        if not 0.0 <= cfg.eps_mistake <= 1.0:
            raise ValueError(f"eps_mistake must be in [0, 1], got {cfg.eps_mistake}")
        if segment_length < 1 or episode_length < 1:
            raise ValueError(
                f"segment_length and episode_length must be >= 1, got "
                f"{segment_length} and {episode_length}"
            )
        if cfg.recent_trajectories < 1:
            raise ValueError(f"recent_trajectories must be >= 1, got {cfg.recent_trajectories}")
        _check_tie(cfg.tie)
        self.cfg = cfg
        self.recent_trajectories = cfg.recent_trajectories
        """the newest episode returns the thresholds' scale is the mean of"""
        self.segment_length = segment_length
        self.episode_length = episode_length
        self.rng = np.random.default_rng(seed)

    def margin(self, recent_returns: Sequence[float]) -> float:
        """Mean recent episode return scaled to one segment, as B-Pref sets its thresholds."""
        mean = recent_mean(recent_returns, self.cfg.recent_trajectories)
        return mean * self.segment_length / self.episode_length

    def answer(
        self, truths: Sequence[QueryTruth], recent_returns: Sequence[float]
    ) -> list[TeacherAnswer]:
        cfg = self.cfg
        margin = self.margin(recent_returns)
        thres_skip = cfg.eps_skip * margin
        # A width, so never negative, even when returns are.
        thres_equal = cfg.eps_equal * abs(margin)
        # Two uniforms per query (choice, mistake), used or not, to keep the stream aligned.
        draws = self.rng.random((len(truths), 2))
        answers = []
        for truth, (u_choice, u_mistake) in zip(truths, draws, strict=True):
            sum0 = float(np.sum(truth.segment_rewards0))
            sum1 = float(np.sum(truth.segment_rewards1))
            if cfg.eps_skip > 0 and max(sum0, sum1) < thres_skip:
                answers.append(TeacherAnswer(Answer.SKIP, False, None))
                continue
            if cfg.eps_equal > 0 and abs(sum0 - sum1) < thres_equal:
                answers.append(TeacherAnswer(Answer.EQUAL, False, None))
                continue
            my0 = _myopic_sum(truth.segment_rewards0, cfg.gamma)
            my1 = _myopic_sum(truth.segment_rewards1, cfg.gamma)
            if math.isinf(cfg.beta):
                choice = _sum_choice(my0, my1, cfg.tie, u_choice)
            else:
                p_second = _sigmoid(cfg.beta * (my1 - my0))
                choice = Answer.SECOND if u_choice < p_second else Answer.FIRST
            if u_mistake < cfg.eps_mistake:
                choice = _flip(choice)
            answers.append(TeacherAnswer(choice, True, is_correct(choice, truth)))
        return answers

    def state_dict(self) -> dict:
        return _rng_state(self.rng, self.kind)

    def load_state_dict(self, d: dict) -> None:
        _load_rng_state(self.rng, self.kind, d)


# ---------------------------------------------------------------------------------------------



def make_teacher(
    cfg: TeacherConfig, seed: int, segment_length: int, episode_length: int
) -> NoisyTeacher | BPrefTeacher:
    if cfg.kind == "noisy":
        return NoisyTeacher(cfg.eps, seed, cfg.recent_trajectories, cfg.tie)
    if cfg.kind == "bpref":
        return BPrefTeacher(cfg, seed, segment_length, episode_length)
    raise ValueError(f"unknown teacher kind {cfg.kind!r}; valid: {', '.join(TEACHER_KINDS)}")

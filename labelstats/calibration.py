"""The teacher-calibration report: how people's answers match the ground truth as the pair's
true return gap shrinks, per labeller and for everyone (docs/QUALITY.md).

It reads label rows as the export writes them (`export_rows`, or a file through
`rundata.export_read`), so a report made over REST and one made from an exported file are
the same. Definitions:

- gap: |first_trajectory_return - second_trajectory_return| / |R_avg|, the whole trajectories'
  gap, as the paper's noisy teacher measures it (`trainer/teachers.py`). R_avg is the one the
  trainer recorded with the query (the export's `r_avg`: the mean return of the run's newest
  trajectories when the round opened). Where it is missing (queries stored before it was
  recorded, schema-2 files) it is estimated per (run, round): the mean trajectory return of the
  newest trajectories (by index) that the round's queries show, as many as the noisy teacher's
  default window (`teacher.recent_trajectories`). An R_avg of 0 makes every
  gap infinite (the noisy teacher's band is then empty).
- outcome, judged on the *segment* returns (what the noisy teacher answers by, and the
  export's `correct`): "correct" or "wrong" for first/second; "equal" is correct on exactly
  equal segment returns and otherwise "unsure", like "can't tell"; first/second on exactly equal
  segment returns is "no verdict" (neither side is right, as the trainer's `is_correct` says);
  "skip" and "no verdict" are left out of everything but the answer counts.
- match ratio: correct / (correct + wrong) with its Wilson interval; can't-tell rate:
  unsure / (correct + wrong + unsure).
- position bias: the share of "left" among left and right clicks, with its Wilson interval and
  the exact binomial test against 0.5.
- eps: `calibration_stats.fit_noisy_teacher` on (gap, outcome) of every non-skip answer.

Only answers to the algorithms' own queries count: gold and practice answers (pairs far apart
by construction, which `labeller_quality` scores apart) are left out, and counted.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from labelstats.calibration_stats import (
    LEVEL,
    EpsFit,
    binomial_test,
    fit_noisy_teacher,
    wilson_interval,
)
from runvocab.config import TeacherConfig

REQUIRED_COLUMNS = (
    "run_id",
    "round",
    "algo",
    "query_id",
    "labeller_id",
    "labeller_name",
    "choice",
    "answer",
    "first_trajectory",
    "second_trajectory",
    "first_segment_return",
    "second_segment_return",
    "first_trajectory_return",
    "second_trajectory_return",
)
"""the export columns a report reads (docs/EXPORT.md)"""
RECENT_TRAJECTORIES = TeacherConfig.recent_trajectories
"""how many of a round's newest trajectories estimate R_avg: the noisy teacher's own window"""
DEFAULT_EDGES: tuple[float, ...] = (
    0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0, 1.5, 2.0, math.inf,
)
"""bin edges of the normalised gap; a bin is [low, high)"""
MAX_BINS = 100
JUDGED = ("correct", "wrong", "unsure")
"""the outcomes the match ratio, the can't-tell rate and the eps fit read"""


@dataclass(frozen=True)
class Rates:
    """How a set of answers went."""

    answers: int
    """every answer, skips included"""
    skipped: int
    no_verdict: int
    """first or second on exactly equal segment returns: no side is right"""
    correct: int
    wrong: int
    cant_tell: int
    """can't tell, or "equal" on segments whose returns differ"""
    match_ratio: float | None
    """correct / (correct + wrong); None when both are 0"""
    match_low: float | None
    match_high: float | None
    cant_tell_rate: float | None
    """cant_tell / (correct + wrong + cant_tell)"""
    cant_tell_low: float | None
    cant_tell_high: float | None


@dataclass(frozen=True)
class Bin:
    """The answers whose normalised gap is in [low, high)."""

    low: float
    high: float | None
    """None: no upper end"""
    rates: Rates
    fitted_match: float | None
    """the match ratio the fitted noisy teacher predicts for these answers' gaps"""


@dataclass(frozen=True)
class PositionBias:
    """How often "left" was clicked, of left and right clicks."""

    left: int
    right: int
    left_share: float | None
    left_low: float | None
    left_high: float | None
    p_value: float
    """exact two-sided binomial test of left_share = 0.5"""


@dataclass(frozen=True)
class Group:
    """One labeller's answers, or everyone's (`labeller_id` None)."""

    name: str
    labeller_id: int | None
    rates: Rates
    fit: EpsFit
    position: PositionBias
    bins: list[Bin]


@dataclass(frozen=True)
class AlgoShare:
    """The queries of one algorithm's runs: the share people answered correctly."""

    algo: str
    runs: int
    queries: int
    rates: Rates
    median_gap: float | None
    """the median normalised gap of its answered pairs (None: none, or all infinite)"""


@dataclass(frozen=True)
class CalibrationReport:
    """The teacher-calibration report of a set of label rows (docs/QUALITY.md)."""

    level: float
    """the confidence level of every interval"""
    edges: list[float | None]
    """the bin edges of the normalised gap; None: no upper end"""
    rows: int
    """label rows read"""
    without_truth: int
    """rows left out for a missing ground-truth return"""
    gold_answers: int
    """gold and practice answers left out (known-answer pairs, not the algorithms' queries)"""
    everyone: Group
    labellers: list[Group]
    """one group per labeller, by labeller id"""
    algos: list[AlgoShare]
    """by algorithm name"""
    runs: list[int] = field(default_factory=list)
    """the runs the rows come from"""


@dataclass(frozen=True)
class _Answer:
    labeller_id: int
    labeller_name: str
    algo: str
    run_id: int
    query_id: int
    gap: float
    outcome: str
    """correct, wrong, unsure or skip"""
    click: str
    """left, right, equal, cant_tell or skip"""


def check_edges(edges: Sequence[float]) -> tuple[float, ...]:
    """`edges` as bin edges: at least two, strictly increasing, from 0; ValueError if not."""
    out = tuple(float(e) for e in edges)
    if len(out) < 2 or len(out) > MAX_BINS + 1:
        raise ValueError(f"bins: give 2 to {MAX_BINS + 1} edges, got {len(out)}")
    if out[0] != 0.0 or any(math.isnan(e) for e in out):
        raise ValueError("bins: the first edge must be 0 (a normalised gap is never negative)")
    if any(b <= a for a, b in zip(out, out[1:], strict=False)):
        raise ValueError("bins: the edges must increase")
    return out


def parse_edges(text: str) -> tuple[float, ...]:
    """Bin edges from text such as "0,0.1,0.2,0.5,1,inf"; ValueError naming the problem."""
    try:
        edges = [float(part) for part in text.split(",") if part.strip()]
    except ValueError as error:
        raise ValueError(f"bins: {text!r} is not a comma-separated list of numbers") from error
    return check_edges(edges)


def missing_columns(columns: Iterable[str]) -> list[str]:
    """The `REQUIRED_COLUMNS` not among `columns`."""
    have = set(columns)
    return [name for name in REQUIRED_COLUMNS if name not in have]


def estimate_r_avg(
    rows: Iterable[Mapping[str, Any]], recent: int = RECENT_TRAJECTORIES
) -> dict[tuple[int, int], float]:
    """Per (run_id, round): the mean return of the `recent` newest trajectories (by index)
    the round's rows show, on either side; rows without a return are ignored."""
    returns: dict[tuple[int, int], dict[int, float]] = {}
    for row in rows:
        seen = returns.setdefault((int(row["run_id"]), int(row["round"])), {})
        for side in ("first", "second"):
            value = row[f"{side}_trajectory_return"]
            if value is not None:
                seen[int(row[f"{side}_trajectory"])] = float(value)
    return {
        key: statistics.fmean(by_index[i] for i in sorted(by_index)[-recent:])
        for key, by_index in returns.items()
        if by_index
    }


def normalised_gap(first_return: float, second_return: float, r_avg: float) -> float:
    """|first - second| / |r_avg|; infinite when r_avg is 0 (every eps then tells them apart)."""
    if r_avg == 0:
        return math.inf
    return abs(first_return - second_return) / abs(r_avg)


def _outcome(row: Mapping[str, Any]) -> str:
    first, second = float(row["first_segment_return"]), float(row["second_segment_return"])
    truth = "equal" if first == second else ("first" if first > second else "second")
    answer = row["answer"]
    if answer == "skip":
        return "skip"
    if answer == "cant_tell" or (answer == "equal" and truth != "equal"):
        return "unsure"
    if truth == "equal" and answer != "equal":
        return "no verdict"
    return "correct" if answer == truth else "wrong"


def _answers(rows: Sequence[Mapping[str, Any]], recent: int) -> tuple[list[_Answer], int]:
    complete = [row for row in rows if all(
        row[name] is not None for name in
        ("first_segment_return", "second_segment_return",
         "first_trajectory_return", "second_trajectory_return"))]
    r_avg = estimate_r_avg(complete, recent)
    answers = [
        _Answer(
            labeller_id=int(row["labeller_id"]),
            labeller_name=str(row["labeller_name"]),
            algo=str(row["algo"]),
            run_id=int(row["run_id"]),
            query_id=int(row["query_id"]),
            gap=normalised_gap(float(row["first_trajectory_return"]),
                               float(row["second_trajectory_return"]),
                               recorded if (recorded := row.get("r_avg")) is not None
                               else r_avg[(int(row["run_id"]), int(row["round"]))]),
            outcome=_outcome(row),
            click=str(row["choice"]),
        )
        for row in complete
    ]
    return answers, len(rows) - len(complete)


def _rates(answers: Sequence[_Answer], level: float) -> Rates:
    correct = sum(a.outcome == "correct" for a in answers)
    wrong = sum(a.outcome == "wrong" for a in answers)
    unsure = sum(a.outcome == "unsure" for a in answers)
    match = wilson_interval(correct, correct + wrong, level)
    no_verdict = sum(a.outcome == "no verdict" for a in answers)
    shown = correct + wrong + unsure
    unsure_interval = wilson_interval(unsure, shown, level)
    return Rates(
        answers=len(answers),
        skipped=len(answers) - shown - no_verdict,
        no_verdict=no_verdict,
        correct=correct,
        wrong=wrong,
        cant_tell=unsure,
        match_ratio=correct / (correct + wrong) if correct + wrong else None,
        match_low=None if match is None else match[0],
        match_high=None if match is None else match[1],
        cant_tell_rate=unsure / shown if shown else None,
        cant_tell_low=None if unsure_interval is None else unsure_interval[0],
        cant_tell_high=None if unsure_interval is None else unsure_interval[1],
    )


def _predicted_match(answers: Sequence[_Answer], fit: EpsFit) -> float | None:
    """E[correct] / E[correct + wrong] of these answers under the fitted teacher."""
    if fit.eps is None or fit.lapse is None or fit.cant_tell is None or not answers:
        return None
    coin = (1.0 - fit.cant_tell) / 2.0
    correct = decided = 0.0
    for answer in answers:
        if answer.gap < fit.eps:
            correct, decided = correct + coin, decided + 2 * coin
        else:
            correct += 1.0 - fit.lapse + fit.lapse * coin
            decided += 1.0 - fit.lapse + 2 * fit.lapse * coin
    return correct / decided if decided else None


def _bins(answers: Sequence[_Answer], edges: Sequence[float], fit: EpsFit,
          level: float) -> list[Bin]:
    out = []
    for low, high in zip(edges, edges[1:], strict=False):
        inside = [a for a in answers if low <= a.gap < high or (high == math.inf == a.gap)]
        out.append(Bin(
            low=low,
            high=None if high == math.inf else high,
            rates=_rates(inside, level),
            fitted_match=_predicted_match([a for a in inside if a.outcome in JUDGED], fit),
        ))
    return out


def _position(answers: Sequence[_Answer], level: float) -> PositionBias:
    left = sum(a.click == "left" for a in answers)
    right = sum(a.click == "right" for a in answers)
    interval = wilson_interval(left, left + right, level)
    return PositionBias(
        left=left,
        right=right,
        left_share=left / (left + right) if left + right else None,
        left_low=None if interval is None else interval[0],
        left_high=None if interval is None else interval[1],
        p_value=binomial_test(left, left + right),
    )


def _group(name: str, labeller_id: int | None, answers: Sequence[_Answer],
           edges: Sequence[float], level: float) -> Group:
    fit = fit_noisy_teacher([(a.gap, a.outcome) for a in answers if a.outcome in JUDGED], level)
    return Group(
        name=name,
        labeller_id=labeller_id,
        rates=_rates(answers, level),
        fit=fit,
        position=_position(answers, level),
        bins=_bins(answers, edges, fit, level),
    )


def _algo(algo: str, answers: Sequence[_Answer], level: float) -> AlgoShare:
    gaps = [a.gap for a in answers if a.outcome in JUDGED and math.isfinite(a.gap)]
    return AlgoShare(
        algo=algo,
        runs=len({a.run_id for a in answers}),
        queries=len({a.query_id for a in answers}),
        rates=_rates(answers, level),
        median_gap=statistics.median(gaps) if gaps else None,
    )


def calibration_report(
    rows: Iterable[Mapping[str, Any]],
    *,
    edges: Sequence[float] = DEFAULT_EDGES,
    level: float = LEVEL,
    recent: int = RECENT_TRAJECTORIES,
) -> CalibrationReport:
    """The report of `rows` (export rows: dicts holding at least `REQUIRED_COLUMNS`; other keys
    are ignored; rows withdrawn by their labeller are left out, gold and practice answers are
    counted in `rows` and `gold_answers` only). ValueError for rows without those columns or
    for bad `edges`."""
    edges = check_edges(edges)
    # An answer taken back (undo) is not an answer.
    table = [row for row in rows if row.get("withdrawn_at") is None]
    if table and (missing := missing_columns(set().union(*(row.keys() for row in table)))):
        raise ValueError(f"the label rows lack the columns {', '.join(missing)}")
    # Gold and practice pairs are far apart by construction, not the algorithms' queries: the
    # labeller quality table scores them apart (`labeller_quality`).
    own = [row for row in table if not row.get("gold") and not row.get("practice")]
    answers, without_truth = _answers(own, recent)
    by_labeller: dict[int, list[_Answer]] = {}
    for answer in answers:
        by_labeller.setdefault(answer.labeller_id, []).append(answer)
    by_algo: dict[str, list[_Answer]] = {}
    for answer in answers:
        by_algo.setdefault(answer.algo, []).append(answer)
    return CalibrationReport(
        level=level,
        edges=[None if e == math.inf else e for e in edges],
        rows=len(table),
        without_truth=without_truth,
        gold_answers=len(table) - len(own),
        everyone=_group("everyone", None, answers, edges, level),
        labellers=[
            # A renamed labeller is shown by its newest name.
            _group(mine[-1].labeller_name, labeller_id, mine, edges, level)
            for labeller_id, mine in sorted(by_labeller.items())
        ],
        algos=[_algo(algo, mine, level) for algo, mine in sorted(by_algo.items())],
        runs=sorted({a.run_id for a in answers}),
    )

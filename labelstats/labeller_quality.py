"""How reliable each labeller is, from label rows as the export writes them.

The operators' labellers page, `GET /api/quality/labellers` and `sepoa report --labellers` all
compute it here from the same rows (`export_rows`, or an export file), so they agree. Answers
taken back (withdrawn) are left out. Per labeller:

- answers, answers per hour of work (pauses longer than `BREAK_S` between answers are not work),
  median answer time (shown to answered; people's answers only);
- accuracy against the hidden true returns on pairs the run's scripted teacher could tell apart
  (the export's `correct` where `distinguishable`), and agreement with that teacher's shadow
  answer (`agrees_with_shadow`);
- accuracy on gold pairs, with its Wilson interval, and whether the labeller is paused;
- can't-tell and skip rates;
- position bias: the share of "left" among left and right clicks, with the exact binomial test
  of 0.5;
- agreement with the other labellers on the queries they share (`labelstats.agreement`).
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Any

from labelstats.agreement import labeller_agreement, standing_answers
from labelstats.calibration_stats import LEVEL, binomial_test, wilson_interval

BREAK_S = 600.0
"""a gap between two answers longer than this is a break, not work"""


@dataclass(frozen=True)
class Share:
    """k of n, with the Wilson interval of k / n."""

    k: int
    n: int
    rate: float | None
    low: float | None
    high: float | None


@dataclass(frozen=True)
class LabellerQuality:
    labeller_id: int
    labeller_name: str
    answers: int
    answers_per_hour: float | None
    """answers over the hours of work (gaps over `BREAK_S` left out); none for one answer"""
    median_answer_s: float | None
    accuracy: Share
    """correct of first/second answers to pairs the scripted teacher could tell apart"""
    shadow_agreement: Share
    """answers equal to the scripted teacher's, where both are first, second or equal"""
    gold_accuracy: Share
    """correct of the answers to gold pairs (skips and the practice round aside)"""
    practice: Share
    """correct of the practice round's answers (`labelqueue.practice`; skips aside)"""
    cant_tell: Share
    """can't-tell answers of all answers"""
    skips: Share
    """skips of all answers"""
    left: Share
    """"left" clicks of left and right clicks"""
    left_p_value: float | None
    """exact two-sided binomial test of left = 0.5"""
    agreement_with_others: float | None
    shared_queries: int
    paused: bool


def _when(value: Any) -> datetime | None:
    if value is None or isinstance(value, datetime):
        return value
    return datetime.fromisoformat(str(value))


def _share(k: int, n: int, level: float) -> Share:
    interval = wilson_interval(k, n, level)
    return Share(k=k, n=n, rate=k / n if n else None,
                 low=None if interval is None else interval[0],
                 high=None if interval is None else interval[1])


def _per_hour(times: Sequence[datetime]) -> float | None:
    ordered = sorted(times)
    gaps = [(b - a).total_seconds() for a, b in zip(ordered, ordered[1:], strict=False)]
    worked = sum(gap for gap in gaps if gap <= BREAK_S)
    return None if worked <= 0 else len(gaps) * 3600.0 / worked


def _quality(rows: Sequence[Mapping[str, Any]], paused: bool, level: float) -> LabellerQuality:
    answered = [_when(row.get("answered_at")) for row in rows]
    seconds = [row["answer_seconds"] for row in rows
               if row.get("source") == "human" and row.get("answer_seconds") is not None]
    judged = [row for row in rows if not row.get("gold") and row.get("distinguishable")
              and row["answer"] in ("first", "second") and row.get("correct") is not None]
    shadow = [row for row in rows if row.get("agrees_with_shadow") is not None]
    gold = [row for row in rows if row.get("gold") and row["answer"] != "skip"
            and not row.get("practice")]
    practice = [row for row in rows if row.get("practice") and row["answer"] != "skip"]
    clicks = [row.get("choice") for row in rows if row.get("choice") in ("left", "right")]
    lefts = clicks.count("left")
    return LabellerQuality(
        labeller_id=int(rows[-1]["labeller_id"]),
        labeller_name=str(rows[-1]["labeller_name"]),
        answers=len(rows),
        answers_per_hour=_per_hour([t for t in answered if t is not None]),
        median_answer_s=statistics.median(seconds) if seconds else None,
        accuracy=_share(sum(bool(row["correct"]) for row in judged), len(judged), level),
        shadow_agreement=_share(sum(bool(row["agrees_with_shadow"]) for row in shadow),
                                len(shadow), level),
        gold_accuracy=_share(sum(bool(row.get("correct")) for row in gold), len(gold), level),
        practice=_share(sum(bool(row.get("correct")) for row in practice), len(practice), level),
        cant_tell=_share(sum(row["answer"] == "cant_tell" for row in rows), len(rows), level),
        skips=_share(sum(row["answer"] == "skip" for row in rows), len(rows), level),
        left=_share(lefts, len(clicks), level),
        left_p_value=binomial_test(lefts, len(clicks)) if clicks else None,
        agreement_with_others=None,
        shared_queries=0,
        paused=paused,
    )


def labeller_quality(rows: Iterable[Mapping[str, Any]], *, paused: Iterable[int] = (),
                     level: float = LEVEL) -> list[LabellerQuality]:
    """Each labeller's quality over `rows` (export rows), by labeller id. `paused`: the ids of
    labellers paused on the run the rows are of."""
    standing = [row for row in rows if row.get("withdrawn_at") is None]
    by_labeller: dict[int, list[Mapping[str, Any]]] = {}
    for row in standing:
        by_labeller.setdefault(int(row["labeller_id"]), []).append(row)
    others = {a.labeller_id: a for a in labeller_agreement(standing_answers(standing))}
    stopped = set(paused)
    out = []
    for labeller_id, mine in sorted(by_labeller.items()):
        quality = _quality(mine, labeller_id in stopped, level)
        shared = others.get(labeller_id)
        if shared is not None:
            quality = replace(quality, agreement_with_others=shared.agreement,
                              shared_queries=shared.shared_queries)
        out.append(quality)
    return out

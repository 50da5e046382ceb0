"""Flagged pairs: answers whose labeller marked the pair as one nobody can judge (clip broken,
agent not visible, other; `runvocab.answers.Flag`), with an optional note. A flag comes with a
skip (`labelqueue.labels.check_flag`), so the trainer never trains on it; the run page counts a
run's flags and lists the latest, and the export has them per row (`flag`, `flag_note`)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from labelqueue.models import Label, Labeller
from labelqueue.transaction import reading
from runvocab.answers import Flag


@dataclass(frozen=True)
class FlaggedLabel:
    label_id: int
    query_id: int
    labeller_id: int
    labeller_name: str
    flag: str
    note: str | None
    answered_at: datetime


@dataclass(frozen=True)
class FlagSummary:
    total: int
    """standing flagged answers on the run"""
    by_flag: dict[str, int]
    """each flag's count, every flag named (0 when unused)"""
    queries: int
    """distinct pairs flagged"""
    latest: list[FlaggedLabel]
    """the newest flagged answers, newest first"""


def flag_summary(session: Session, *, run_id: int, latest: int = 10) -> FlagSummary:
    """The run's flagged answers that stand (not taken back): counts and the newest few."""
    flagged = (Label.run_id == run_id) & Label.flag.is_not(None) & Label.withdrawn_at.is_(None)
    with reading(session):
        counts: dict[Flag | None, int] = {
            row[0]: int(row[1]) for row in session.execute(
                select(Label.flag, func.count()).where(flagged).group_by(Label.flag))}
        queries = session.scalar(select(func.count(func.distinct(Label.query_id)))
                                 .where(flagged)) or 0
        rows = session.execute(
            select(Label.id, Label.query_id, Label.labeller_id, Labeller.name, Label.flag,
                   Label.flag_note, Label.answered_at)
            .join(Labeller, Labeller.id == Label.labeller_id)
            .where(flagged).order_by(Label.id.desc()).limit(latest)).all()
    by_flag = {flag.value: int(counts.get(flag, 0)) for flag in Flag}
    return FlagSummary(
        total=sum(by_flag.values()), by_flag=by_flag, queries=int(queries),
        latest=[FlaggedLabel(r[0], r[1], r[2], r[3], Flag(r[4]).value, r[5], r[6])
                for r in rows])

"""Label statistics read from the labels table: a run's labelling throughput and a labeller's
own label count.

Both count standing labels only: an answer taken back (`Label.withdrawn_at`) was not given. The
throughput is worked out in SQL (counts per bucket and per source) and from a bounded read (the
median answer time of the latest `MEDIAN_OF` human answers), in one read-only transaction. Its
`fingerprint` (how many labels, the last id, how many taken back) changes with every new or
withdrawn label, so a caller may keep an answer and have it back while nothing changed. The SQL
that reads times differs by dialect; it stays in this module.
"""

from __future__ import annotations

import statistics
from collections import Counter
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import BigInteger, ColumnElement, Float, Integer, cast, func, select
from sqlalchemy.orm import InstrumentedAttribute, Session

from labelqueue.errors import NotFound
from labelqueue.models import Label, LabelSource, Run
from labelqueue.transaction import reading

STANDING = Label.withdrawn_at.is_(None)
"""a label that counts: not taken back"""
MEDIAN_OF = 1000
"""the median answer time is that of the run's latest this many timed human answers"""

Fingerprint = tuple[int, int, int]


@dataclass(frozen=True)
class LabelThroughput:
    run_id: int
    bucket_s: int
    fingerprint: Fingerprint
    """the run's labels, its last label id, its labels taken back, when this was counted"""
    by_source: dict[str, int]
    """standing labels per source (every `LabelSource`, 0 if none)"""
    median_answer_s: float | None
    buckets: list[tuple[datetime, int]]
    """(bucket start, labels answered in it), oldest first; empty buckets left out"""

    @property
    def total(self) -> int:
        return sum(self.by_source.values())


def _epoch_bucket(dialect: str, bucket_s: int) -> ColumnElement[int]:
    """The number of the `bucket_s`-second bucket (aligned to the epoch) of a label's answer."""
    if dialect == "sqlite":  # answered_at is stored as UTC text: strftime reads it as UTC
        seconds = cast(func.strftime("%s", Label.answered_at), Integer)
    else:
        seconds = cast(func.floor(func.extract("epoch", Label.answered_at)), BigInteger)
    return seconds // bucket_s  # whole seconds: flooring them first changes no bucket


def _answer_s(dialect: str) -> ColumnElement[float]:
    """answered_at - shown_at in seconds, to the microsecond."""
    if dialect == "sqlite":
        # Stored as 'YYYY-MM-DD HH:MM:SS.ffffff' (UTC): whole seconds, then the fraction
        # (julianday keeps milliseconds only).
        def seconds(column: InstrumentedAttribute[Any]) -> ColumnElement[float]:
            return cast(cast(func.strftime("%s", column), Integer)
                        + cast(func.substr(column, 20), Float), Float)
        return seconds(Label.answered_at) - seconds(Label.shown_at)
    return cast(func.extract("epoch", Label.answered_at - Label.shown_at), Float)


def _fingerprint(session: Session, run_id: int) -> Fingerprint:
    """The run's labels, its last label id, and its labels taken back: a new or withdrawn label
    changes it. Only a label the trainer has not taken can be withdrawn (`labelqueue.undo`), so
    the last count reads the run's untaken labels only (the rest is counted from the index)."""
    count, last = session.execute(
        select(func.count(), func.coalesce(func.max(Label.id), 0)).where(Label.run_id == run_id)
    ).one()
    withdrawn = session.scalar(
        select(func.count(Label.withdrawn_at))
        .where(Label.run_id == run_id, Label.consumed_at.is_(None))
    )
    return int(count), int(last), int(withdrawn or 0)


def _count(session: Session, *, run_id: int, bucket_s: int, seen: Fingerprint) -> LabelThroughput:
    dialect = session.get_bind().dialect.name
    of_run = (Label.run_id == run_id) & STANDING
    bucket = _epoch_bucket(dialect, bucket_s).label("bucket")
    per_bucket: Counter[int] = Counter()
    by_source = {source.value: 0 for source in LabelSource}
    for number, source, n in session.execute(  # one pass over the run's labels
        select(bucket, Label.source, func.count()).where(of_run).group_by(bucket, Label.source)
    ):
        per_bucket[number] += n
        by_source[LabelSource(source).value] += n
    # Only people's answers say how long a person takes; a scripted teacher answers at once.
    # The latest MEDIAN_OF: the pace of the people labelling now, in a bounded read (newest
    # first by the primary key: `run_id + 0` keeps the planner off the run's index, which would
    # sort all the run's labels).
    answer_s = [float(seconds) for seconds in session.scalars(
        select(_answer_s(dialect))
        .where((Label.run_id + 0) == run_id, STANDING, Label.source == LabelSource.HUMAN,
               Label.shown_at.is_not(None))
        .order_by(Label.id.desc()).limit(MEDIAN_OF)
    )]
    return LabelThroughput(
        run_id=run_id,
        bucket_s=bucket_s,
        fingerprint=seen,
        by_source=by_source,
        median_answer_s=statistics.median(answer_s) if answer_s else None,
        buckets=[(datetime.fromtimestamp(b * bucket_s, UTC), n)
                 for b, n in sorted(per_bucket.items())],
    )


def label_throughput(
    session: Session, *, run_id: int, bucket_s: int, kept: LabelThroughput | None = None
) -> LabelThroughput:
    """How fast the run gets its labels, by `bucket_s`-second buckets of answer time. `kept`, an
    answer counted before, comes back as it is when the run's labels have not changed since.
    NotFound for an unknown run."""
    with reading(session):
        if session.scalar(select(Run.id).where(Run.id == run_id)) is None:
            raise NotFound(f"run {run_id} does not exist")
        seen = _fingerprint(session, run_id)
        if kept is not None and (kept.run_id, kept.bucket_s, kept.fingerprint) == (
                run_id, bucket_s, seen):
            return kept
        # One snapshot: the fingerprint describes the labels counted.
        return _count(session, run_id=run_id, bucket_s=bucket_s, seen=seen)


def labels_given(session: Session, *, labeller_id: int) -> int:
    """The labeller's standing labels, over all runs."""
    with reading(session):
        count = session.scalar(
            select(func.count()).select_from(Label)
            .where(Label.labeller_id == labeller_id, STANDING)
        )
    return int(count or 0)

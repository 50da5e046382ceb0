"""Label statistics: a run's labelling throughput (operator) and a labeller's own label count.

Both count standing labels only: an answer taken back (`Label.withdrawn_at`) was not given.
The run page polls the throughput every 5 s, so it is worked out in SQL (counts per bucket and
per source) and from a bounded read (the median answer time of the latest `MEDIAN_OF` human
answers) in one read-only transaction (`services.reading`), and the answer is kept by the run's
labels' fingerprint (`_fingerprint`: how many, the last id, how many taken back): the pages that
ask while nothing has changed share one computation.
"""

from __future__ import annotations

import statistics
import threading
from collections import Counter, OrderedDict
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from sqlalchemy import BigInteger, ColumnElement, Float, Integer, cast, func, select
from sqlalchemy.orm import InstrumentedAttribute, Session

from labelqueue import Label, LabelSource
from server import services
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.schemas import LabelCount, RunId, Throughput, ThroughputBucket, errors

router = APIRouter(prefix="/api", tags=["stats"])

STANDING = Label.withdrawn_at.is_(None)
"""a label that counts: not taken back"""
MEDIAN_OF = 1000
"""the median answer time is that of the run's latest this many timed human answers"""
_CACHED = 64
"""throughput answers kept, by database, run and bucket length (a page asks for one length)"""
_cache: OrderedDict[tuple[str, int, int], tuple[tuple[int, int, int], Throughput]] = OrderedDict()
_cache_lock = threading.Lock()


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


def _fingerprint(session: Session, run_id: int) -> tuple[int, int, int]:
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


def _throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
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
    return Throughput(
        run_id=run_id,
        bucket_s=bucket_s,
        total=sum(by_source.values()),
        by_source=by_source,
        median_answer_s=statistics.median(answer_s) if answer_s else None,
        buckets=[ThroughputBucket(t=datetime.fromtimestamp(b * bucket_s, UTC), labels=n)
                 for b, n in sorted(per_bucket.items())],
    )


def label_throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
    services.get_run(session, run_id=run_id)  # NotFound -> 404
    key = (str(session.get_bind().engine.url), run_id, bucket_s)
    with services.reading(session):
        seen = _fingerprint(session, run_id)
        with _cache_lock:
            kept = _cache.get(key)
        if kept is not None and kept[0] == seen:
            return kept[1]
        # One snapshot: the fingerprint describes the labels counted.
        stats = _throughput(session, run_id=run_id, bucket_s=bucket_s)
    with _cache_lock:
        _cache[key] = (seen, stats)
        _cache.move_to_end(key)
        while len(_cache) > _CACHED:
            _cache.popitem(last=False)
    return stats


def labels_given(session: Session, *, labeller_id: int) -> int:
    with services.reading(session):
        count = session.scalar(
            select(func.count()).select_from(Label)
            .where(Label.labeller_id == labeller_id, STANDING)
        )
    return int(count or 0)


@router.get(
    "/runs/{run_id}/throughput", response_model=Throughput, responses=errors(401, 403, 404, 422)
)
def get_throughput(
    run_id: RunId,
    session: SessionDep,
    _: OperatorDep,
    bucket_s: Annotated[int, Query(ge=1, le=86_400)] = 60,
) -> Throughput:
    """Labels per time bucket (by answer time), totals by source, median human answer time."""
    return label_throughput(session, run_id=run_id, bucket_s=bucket_s)


@router.get("/label/count", response_model=LabelCount, responses=errors(401, 403))
def get_label_count(session: SessionDep, caller: LabellerDep) -> LabelCount:
    """How many labels the caller has given, over all runs."""
    assert caller.labeller_id is not None
    return LabelCount(labels=labels_given(session, labeller_id=caller.labeller_id))

"""Label statistics: a run's labelling throughput (operator) and a labeller's own label count.

Both read the labels table once and commit at once (`services.reading`), so SQLite's write lock
is never held while the numbers are worked out in Python.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Query
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from labelqueue import Label, LabelSource
from server import services
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.schemas import LabelCount, RunId, Throughput, ThroughputBucket, errors

router = APIRouter(prefix="/api", tags=["stats"])


def bucket_start(when: datetime, bucket_s: int) -> datetime:
    """The start of the `bucket_s`-second bucket `when` falls in (buckets align to the epoch)."""
    return datetime.fromtimestamp(math.floor(when.timestamp() / bucket_s) * bucket_s, UTC)


def label_throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
    services.get_run(session, run_id=run_id)  # NotFound -> 404
    with services.reading(session):
        rows = session.execute(
            select(Label.source, Label.shown_at, Label.answered_at).where(Label.run_id == run_id)
        ).all()
    per_bucket = Counter(bucket_start(answered, bucket_s) for _, _, answered in rows)
    by_source = Counter(LabelSource(source).value for source, _, _ in rows)
    # Only people's answers say how long a person takes; a scripted teacher answers at once.
    answer_s = [
        (answered - shown).total_seconds()
        for source, shown, answered in rows
        if source == LabelSource.HUMAN and shown is not None
    ]
    return Throughput(
        run_id=run_id,
        bucket_s=bucket_s,
        total=len(rows),
        by_source={source.value: by_source[source.value] for source in LabelSource},
        median_answer_s=statistics.median(answer_s) if answer_s else None,
        buckets=[ThroughputBucket(t=t, labels=n) for t, n in sorted(per_bucket.items())],
    )


def labels_given(session: Session, *, labeller_id: int) -> int:
    with services.reading(session):
        count = session.scalar(
            select(func.count()).select_from(Label).where(Label.labeller_id == labeller_id)
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

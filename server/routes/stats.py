"""Label statistics: a run's labelling throughput (operator) and a labeller's own label count
(`runviews.label_stats`). The run page polls the throughput every 5 s: the answer is kept by
the run's labels' fingerprint, so the pages that ask while nothing has changed share one
computation.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Annotated

from fastapi import APIRouter, Query
from sqlalchemy.orm import Session

from runviews.label_stats import LabelThroughput, label_throughput, labels_given
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.label_schemas import LabelCount
from server.schemas import RunId, Throughput, ThroughputBucket, errors

router = APIRouter(prefix="/api", tags=["stats"])

_CACHED = 64
"""throughput answers kept, by database, run and bucket length (a page asks for one length)"""
_cache: OrderedDict[tuple[str, int, int], LabelThroughput] = OrderedDict()
_cache_lock = threading.Lock()


def run_throughput(session: Session, *, run_id: int, bucket_s: int) -> Throughput:
    """The run's throughput, counted again only when its labels changed since the last ask."""
    key = (str(session.get_bind().engine.url), run_id, bucket_s)
    with _cache_lock:
        kept = _cache.get(key)
    counted = label_throughput(session, run_id=run_id, bucket_s=bucket_s, kept=kept)
    if counted is not kept:
        with _cache_lock:
            _cache[key] = counted
            _cache.move_to_end(key)
            while len(_cache) > _CACHED:
                _cache.popitem(last=False)
    return Throughput(
        run_id=run_id,
        bucket_s=bucket_s,
        total=counted.total,
        by_source=counted.by_source,
        median_answer_s=counted.median_answer_s,
        buckets=[ThroughputBucket(t=start, labels=n) for start, n in counted.buckets],
    )


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
    return run_throughput(session, run_id=run_id, bucket_s=bucket_s)


@router.get("/label/count", response_model=LabelCount, responses=errors(401, 403))
def get_label_count(session: SessionDep, caller: LabellerDep) -> LabelCount:
    """How many labels the caller has given, over all runs."""
    assert caller.labeller_id is not None
    return LabelCount(labels=labels_given(session, labeller_id=caller.labeller_id))

"""Learning curves in the database, so the server draws them without reading trainer files."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from labelqueue.coerce import json_object
from labelqueue.models import Metric, MetricStream, Run
from labelqueue.transaction import changed, detach, get_row, reading, transaction


def write_metrics(
    session: Session,
    *,
    run_id: int,
    stream: MetricStream | str,
    step: int,
    values: Mapping[str, Any],
) -> None:
    """Record one point of a curve; a step written again (after a resume) replaces the old one."""
    stream = MetricStream(stream)
    clean = json_object(values)
    with transaction(session):
        replaced = changed(
            session,
            update(Metric)
            .where(Metric.run_id == run_id, Metric.stream == stream, Metric.step == step)
            .values({Metric.values: clean}),
        )
        if not replaced:
            get_row(session, Run, run_id)
            session.add(Metric(run_id=run_id, stream=stream, step=int(step), values=clean))


def read_metrics(
    session: Session,
    *,
    run_id: int,
    stream: MetricStream | str,
    after_step: int | None = None,
) -> list[Metric]:
    """A run's curve for one stream, by step; only the steps after `after_step` when given."""
    condition = [Metric.run_id == run_id, Metric.stream == MetricStream(stream)]
    if after_step is not None:
        condition.append(Metric.step > after_step)
    with reading(session):
        rows = list(
            session.scalars(
                select(Metric)
                .where(*condition)
                .order_by(Metric.step)
                .execution_options(populate_existing=True)
            )
        )
        detach(session, *rows)
    return rows

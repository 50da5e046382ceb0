"""Learning curves go through the database for the server to draw."""

from __future__ import annotations

import numpy as np
import pytest
from queue_helpers import running_run
from sqlalchemy.orm import Session

from labelqueue import MetricStream, NotFound, read_metrics, write_metrics


def test_curves_are_read_back_by_stream_and_step(session: Session) -> None:
    run = running_run(session)
    for step in (3000, 1000, 2000):
        write_metrics(
            session, run_id=run.id, stream="episodes", step=step, values={"return": step / 10}
        )
    write_metrics(session, run_id=run.id, stream=MetricStream.EVAL, step=2000, values={"r": 1})

    episodes = read_metrics(session, run_id=run.id, stream="episodes")
    assert [(m.step, m.values["return"]) for m in episodes] == [
        (1000, 100.0),
        (2000, 200.0),
        (3000, 300.0),
    ]
    newer = read_metrics(session, run_id=run.id, stream="episodes", after_step=1000)
    assert [m.step for m in newer] == [2000, 3000]
    assert [m.values for m in read_metrics(session, run_id=run.id, stream="eval")] == [{"r": 1}]
    assert read_metrics(session, run_id=run.id, stream="rounds") == []


def test_a_step_written_again_replaces_the_old_point(session: Session) -> None:
    # A run resumed from a checkpoint repeats the episodes after it.
    run = running_run(session)
    write_metrics(session, run_id=run.id, stream="episodes", step=1000, values={"return": 1.0})
    write_metrics(session, run_id=run.id, stream="episodes", step=1000, values={"return": 2.0})
    [point] = read_metrics(session, run_id=run.id, stream="episodes")
    assert point.values == {"return": 2.0}


def test_values_are_stored_as_strict_json(session: Session) -> None:
    run = running_run(session)
    values = {
        "return": np.float32(1.5),
        "labels": np.int64(7),
        "accuracy": float("nan"),
        "success": True,
        "per_member": [np.float64(0.25), float("inf")],
    }
    write_metrics(session, run_id=run.id, stream="rounds", step=5, values=values)
    [point] = read_metrics(session, run_id=run.id, stream="rounds")
    assert point.values == {
        "return": 1.5,
        "labels": 7,
        "accuracy": None,
        "success": True,
        "per_member": [0.25, None],
    }


def test_unknown_runs_and_streams_are_refused(session: Session) -> None:
    with pytest.raises(NotFound):
        write_metrics(session, run_id=42, stream="eval", step=0, values={})
    with pytest.raises(ValueError):
        write_metrics(session, run_id=42, stream="losses", step=0, values={})

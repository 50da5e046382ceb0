"""Small builders shared by the queue tests."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from labelqueue import Run, TeacherKind, claim_run, create_run


def running_run(
    session: Session, *, teacher: TeacherKind = TeacherKind.SCRIPTED, worker_id: str = "worker-a"
) -> Run:
    """A run claimed by `worker_id`; assumes no other run is queued."""
    run = create_run(
        session, name="r", task="dmc:cheetah_run", algo="pebble", budget=100, teacher=teacher
    )
    claimed = claim_run(session, worker_id=worker_id)
    assert claimed is not None and claimed.id == run.id
    return claimed


def query_spec(position: int, *, round: int = 0, **overrides: Any) -> dict[str, Any]:
    """A pushable query; clips included, so human-taught runs serve it too."""
    spec: dict[str, Any] = {
        "round": round,
        "position": position,
        "step": 1000,
        "segment_length": 50,
        "first_trajectory": 2 * position,
        "first_start": 10,
        "second_trajectory": 2 * position + 1,
        "second_start": 20,
        "first_segment_return": 1.5,
        "second_segment_return": 2.5,
        "first_trajectory_return": 100.0,
        "second_trajectory_return": 120.0,
        "first_clip": f"r{round}/q{position}-a.mp4",
        "second_clip": f"r{round}/q{position}-b.mp4",
        "model_p": 0.6,
        "score": 0.1,
        "rule": "disagreement",
    }
    return spec | overrides

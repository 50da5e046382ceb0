"""Operator endpoints over stored labels: a run's flagged pairs (counted on its run page)."""

from __future__ import annotations

from fastapi import APIRouter

from labelqueue import read_run
from labelqueue.flags import FlagSummary, flag_summary
from server.deps import OperatorDep, SessionDep
from server.schemas import RunId, errors

router = APIRouter(prefix="/api", tags=["labels"])


@router.get("/runs/{run_id}/flags", response_model=FlagSummary,
            responses=errors(401, 403, 404, 422))
def get_flags(run_id: RunId, session: SessionDep, _: OperatorDep) -> FlagSummary:
    """The pairs labellers flagged on the run (clip broken, agent not visible, other; each with
    a skip, never trained on): counts per flag and the ten newest with their notes. Answers
    taken back do not count."""
    read_run(session, run_id=run_id)  # 404 for an unknown run
    return flag_summary(session, run_id=run_id)

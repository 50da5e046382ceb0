"""Operator endpoints over stored labels: a run's flagged pairs (counted on its run page) and
the label browser's list and single label (`runviews.label_browser`). True returns are in
these answers, so every one is for operators only."""

from __future__ import annotations

import time
from dataclasses import dataclass, fields
from typing import Annotated

from fastapi import APIRouter, Path, Query

from labelqueue import read_run
from runviews.flags import FlagSummary, flag_summary
from runviews.label_browser import (
    MAX_PAGE,
    LabelDetail,
    LabelPage,
    browse_labels,
    label_detail,
)
from server import clips
from server.deps import OperatorDep, SessionDep, SettingsDep
from server.schemas import INT32_MAX, RunFilter, RunId, errors

router = APIRouter(prefix="/api", tags=["labels"])


@router.get("/runs/{run_id}/flags", response_model=FlagSummary,
            responses=errors(401, 403, 404, 422))
def get_flags(run_id: RunId, session: SessionDep, _: OperatorDep) -> FlagSummary:
    """The pairs labellers flagged on the run (clip broken, agent not visible, other; each with
    a skip, never trained on): counts per flag and the ten newest with their notes. Answers
    taken back do not count."""
    read_run(session, run_id=run_id)  # 404 for an unknown run
    return flag_summary(session, run_id=run_id)


@dataclass(frozen=True)
class LabelView(LabelDetail):
    first_clip_url: str | None = None
    """a signed URL of the first segment's clip (none before it is rendered)"""
    second_clip_url: str | None = None


Flt = Annotated[bool | None, Query(description="true or false; left out: either")]


@router.get("/labels", response_model=LabelPage, responses=errors(401, 403, 404, 422))
def get_labels(
    session: SessionDep,
    _: OperatorDep,
    run_id: RunFilter = None,
    labeller_id: Annotated[int | None, Query(ge=1, le=INT32_MAX)] = None,
    correct: Flt = None,
    flagged: Flt = None,
    gold: Flt = None,
    withdrawn: Annotated[bool, Query(description="list answers taken back too")] = False,
    before: Annotated[int | None, Query(ge=1, le=INT32_MAX,
                                        description="labels older than this id")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE)] = 50,
) -> LabelPage:
    """Stored labels, newest first (the label browser): by run, labeller, correctness against
    the hidden truth (first, second and equal answers only), flag and gold. Operators only:
    this is where true returns are."""
    return browse_labels(session, run_id=run_id, labeller_id=labeller_id, correct=correct,
                         flagged=flagged, gold=gold, withdrawn=withdrawn, before=before,
                         limit=limit)


@router.get("/labels/{label_id}", response_model=LabelView,
            responses=errors(401, 403, 404, 422))
def get_label(label_id: Annotated[int, Path(ge=1, le=INT32_MAX)], session: SessionDep,
              settings: SettingsDep, _: OperatorDep) -> LabelView:
    """One label with its pair: both clips (signed URLs), where each segment starts, the
    answer, the scripted shadow label, the true segment returns and the answer they call for."""
    detail = label_detail(session, label_id=label_id)
    urls: dict[str, str | None] = {"first": None, "second": None}
    if detail.has_clips:
        now = time.time()
        urls = {side: clips.signed_clip_url(settings=settings, query_id=detail.label.query_id,
                                            side=side, now=now) for side in clips.SIDES}
    return LabelView(**{f.name: getattr(detail, f.name) for f in fields(detail)},
                     first_clip_url=urls["first"], second_clip_url=urls["second"])

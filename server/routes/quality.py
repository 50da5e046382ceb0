"""Operator endpoints of label quality (docs/QUALITY.md), for one run's labels or all of them:
the teacher-calibration report, as data and as the figure the run page shows; agreement between
labellers; each labeller's reliability; lifting a gold-threshold pause.

The report is made from the same rows a label export holds (`export_rows`, read in short
transactions of their own), so it equals `sepoa report --calibration` on an export of the same
labels. Working it out takes a fraction of a second per labeller of CPU; drawing it about as
much again, so the figure is drawn by the run page's drawing process (`server.curves`), once per
report: pages asking again for unchanged labels get the PNG drawn before.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import Response
from sqlalchemy.orm import Session

from labelqueue import Invalid, NotFound, export_rows, lift_pause, paused_labellers
from labelstats.agreement import AgreementReport, agreement_report
from labelstats.calibration import (
    DEFAULT_EDGES,
    MAX_BINS,
    CalibrationReport,
    calibration_report,
    parse_edges,
)
from labelstats.labeller_quality import LabellerQuality, labeller_quality
from server import curves
from server.deps import OperatorDep, SessionDep
from server.schemas import LabellerId, RunFilter, RunId, errors

router = APIRouter(prefix="/api/quality", tags=["quality"])

_EDGE = r"(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?|inf"
_ZERO = r"(0+(\.0*)?|\.0+)([eE][+-]?\d+)?"
BINS_PATTERN = rf"^ *{_ZERO} *(, *({_EDGE}) *){{1,{MAX_BINS}}}$"
"""what `parse_edges` takes, but that the edges must increase: 2 to MAX_BINS + 1 numbers, 0
first"""
Bins = Annotated[
    str | None,
    Query(
        max_length=2000,
        description=f"bin edges of the normalised gap: 2 to {MAX_BINS + 1} comma-separated "
        "numbers (or inf), the first 0, each larger than the one before, e.g. "
        "0,0.1,0.2,0.5,1,inf (default: 0, 0.05, 0.1, ..., 2, inf)",
        json_schema_extra={"pattern": BINS_PATTERN},
    ),
]


def report_of(session: Session, *, run_id: int | None, bins: str | None) -> CalibrationReport:
    """The report of a run's labels (or all): NotFound for an unknown run, Invalid for bad
    bins (checked first, before any row is read)."""
    try:
        edges = DEFAULT_EDGES if bins is None else parse_edges(bins)
    except ValueError as err:
        raise Invalid(str(err)) from None
    return calibration_report(export_rows(session, run_id=run_id), edges=edges)


@router.get("/calibration", response_model=CalibrationReport,
            responses=errors(401, 403, 404, 422))
def get_calibration(
    session: SessionDep, _: OperatorDep, run_id: RunFilter = None, bins: Bins = None
) -> CalibrationReport:
    """Match ratio and can't-tell rate against the true return gap over R_avg, the noisy
    teacher's eps fitted to the answers, and position bias, per labeller and for everyone;
    the share answered correctly per algorithm."""
    return report_of(session, run_id=run_id, bins=bins)


@router.get("/calibration.png", response_class=Response,
            responses=errors(401, 403, 404, 422, also={200: {"content": {"image/png": {}}}}))
def get_calibration_png(
    session: SessionDep, _: OperatorDep, run_id: RunFilter = None, bins: Bins = None
) -> Response:
    """The report's figure, as `sepoa report --calibration` draws it."""
    report = report_of(session, run_id=run_id, bins=bins)
    title = "All runs" if run_id is None else f"Run {run_id}"
    png = curves.calibration_png(report, title=f"Teacher calibration · {title}")
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.get("/agreement", response_model=AgreementReport, responses=errors(401, 403, 404, 422))
def get_agreement(session: SessionDep, _: OperatorDep, run_id: RunFilter = None) -> AgreementReport:
    """Agreement between labellers who answered the same queries (a run's
    `feedback.labels_per_query` above 1, and gold pairs): pairwise agreement and Fleiss' κ for
    all queries and per round, and each labeller's agreement with the others."""
    return agreement_report(export_rows(session, run_id=run_id))


@router.get("/labellers", response_model=list[LabellerQuality],
            responses=errors(401, 403, 404, 422))
def get_labeller_quality(
    session: SessionDep, _: OperatorDep, run_id: RunFilter = None
) -> list[LabellerQuality]:
    """Per labeller: answers, pace, accuracy against the hidden truth and the scripted teacher,
    gold accuracy, can't-tell and skip rates, position bias, agreement with others, and (for one
    run) whether the gold threshold paused them."""
    rows = export_rows(session, run_id=run_id)
    paused = [] if run_id is None else [p.labeller_id
                                        for p in paused_labellers(session, run_id=run_id)]
    return labeller_quality(rows, paused=paused)


@router.delete("/runs/{run_id}/pauses/{labeller_id}", status_code=204,
               responses=errors(401, 403, 404, 422))
def delete_pause(run_id: RunId, labeller_id: LabellerId, session: SessionDep,
                 _: OperatorDep) -> Response:
    """Let a labeller the gold threshold paused answer the run's queries again (their answers
    and gold record stay). 404 when the labeller is not paused on the run."""
    if not lift_pause(session, run_id=run_id, labeller_id=labeller_id):
        raise NotFound(f"labeller {labeller_id} is not paused on run {run_id}")
    return Response(status_code=204)

"""Taking an answer back: a labeller withdraws its last answer for a few seconds after giving it
(`labelqueue.undo`), and gets the pair back to answer again."""

from __future__ import annotations

from fastapi import APIRouter, Response

from server import services
from server.deps import BEARER_SECURITY, LabellerCallDep
from server.label_schemas import TakeBack, TakenBack
from server.routes.label import json_response
from server.schemas import QueryId, errors

router = APIRouter(prefix="/api", tags=["label"])


@router.post(
    "/label/{query_id:int}/withdraw",
    response_model=TakenBack,
    responses=errors(400, 401, 403, 404, 409, 413, 422),
    openapi_extra=BEARER_SECURITY,
)
async def withdraw(
    query_id: QueryId, call: LabellerCallDep, body: TakeBack | None = None
) -> Response:
    """Take back the caller's answer to the query, within 10 s of giving it and while the
    trainer has not taken it: the label stays, withdrawn (the export shows it), and the query is
    leased to the caller again. 404 when the caller has no standing answer to it; 409 when it is
    too late, the trainer took the answer, the run was stopped, the round closed, another
    labeller holds the pair now, or it is a practice answer of an entry test, each said
    plainly."""
    label, query = await call.serve(services.take_back_answer, query_id=query_id,
                                    keep=body.keep if body else None)
    assert label.withdrawn_at is not None
    return json_response(TakenBack(label_id=label.id, withdrawn_at=label.withdrawn_at,
                                   query=query))

"""A study's list to pay from (operators): `GET /api/invites/{id}/participants` as JSON or CSV
(`crowdstudy.participants`), its page `/invites/{id}/participants`, and many completion codes
checked at once (`POST /api/invites/verify-codes`)."""

from __future__ import annotations

import csv
import io
from typing import Annotated, Literal

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse, Response

from crowdstudy.participants import CSV_COLUMNS, participants, verify_codes
from server.deps import OperatorDep, SessionDep
from server.routes.invites import InviteId
from server.routes.pages import page
from server.schemas import errors
from server.study_schemas import CodeCheckOut, CodesRequest, ParticipantOut

router = APIRouter()
pages = APIRouter(include_in_schema=False)


@router.get(
    "/api/invites/{invite_id}/participants",
    tags=["invites"],
    response_model=list[ParticipantOut],
    responses=errors(401, 403, 404, 422, also={200: {"content": {"text/csv": {}}}}),
)
def get_participants(
    invite_id: InviteId, session: SessionDep, _: OperatorDep,
    format: Annotated[Literal["json", "csv"], Query(description="json, or csv to save")] = "json",
) -> list[ParticipantOut] | Response:
    """Everyone who joined the study, in the order they joined: participant id, labeller,
    when they joined, time on task, answers (decisive, equal, can't tell, skips, flags and
    practice apart), gold score, whether check pairs paused them, and their completion code
    with whether it is earned (`code_valid`: pay those). `format=csv` gives the same as a
    file."""
    rows = [ParticipantOut.model_validate(p) for p in participants(session, invite_id=invite_id)]
    if format == "json":
        return rows
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(CSV_COLUMNS)
    for row in rows:
        values = row.model_dump(mode="json")
        writer.writerow(["" if values[c] is None else values[c] for c in CSV_COLUMNS])
    return Response(out.getvalue(), media_type="text/csv", headers={
        "Content-Disposition": f'attachment; filename="invite-{invite_id}-participants.csv"'})


@router.post(
    "/api/invites/verify-codes",
    tags=["invites"],
    response_model=list[CodeCheckOut],
    responses=errors(400, 401, 403, 404, 413, 422),
)
def post_verify_codes(body: CodesRequest, session: SessionDep,
                      _: OperatorDep) -> list[CodeCheckOut]:
    """Many completion codes at once, as participants handed them in: for each, whose it is
    and whether it is earned (`valid`: pay them); `why` "unknown" for nobody's code,
    "not_complete" for a study not complete yet. Blank codes are left out. With `invite_id`
    (404 for an unknown one), a code of another invite's participant is "other_study", not
    valid for this one."""
    return [CodeCheckOut.model_validate(c)
            for c in verify_codes(session, body.codes, invite_id=body.invite_id)]


@pages.get("/invites/{invite_id}/participants", response_class=HTMLResponse)
def participants_page(request: Request, invite_id: int) -> HTMLResponse:
    """The participants of a study, to pay from: the list, its CSV, and a box to check many
    codes at once (the page fetches them with the operator's token)."""
    return page(request, "participants.html", nav="runs", invite_id=invite_id)

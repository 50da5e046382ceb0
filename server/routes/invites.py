"""Invite links: operators make, list and revoke them; whoever opens one joins as a labeller.

`/join/<code>` is a page: an open link shows the run's instruction and a short how-to while the
page's script joins (`POST /api/join/<code>`), keeps the new labeller's token in the browser and
offers the label page. A link that no longer admits anyone answers a page that says why (410),
an unknown one a page that says so (404): never a stack trace.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.responses import HTMLResponse

from labelqueue import (
    Invite,
    NotFound,
    create_invite,
    invite_state,
    join_invite,
    labeller_progress,
    list_invites,
    read_invite,
    revoke_invite,
)
from labelqueue.invites import CLOSED_TEXT
from labelqueue.models import utcnow
from runvocab.instructions import run_instruction
from server import services
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.routes.pages import page
from server.schemas import (
    INT32_MAX,
    ErrorOut,
    InviteCreate,
    InviteOut,
    JoinedOut,
    JoinRequest,
    ProgressOut,
    errors,
)

router = APIRouter()

InviteId = Annotated[int, Path(ge=1, le=INT32_MAX, description="the invite's id")]
InviteCode = Annotated[str, Path(max_length=64, description="the code in the invite link")]


def invite_out(request: Request, invite: Invite) -> InviteOut:
    fields = {column: getattr(invite, column) for column in InviteOut.model_fields
              if column not in ("url", "state")}
    return InviteOut(**fields, url=str(request.url_for("join_page", code=invite.code)),
                     state=invite_state(invite))


@router.post(
    "/api/invites",
    tags=["invites"],
    status_code=201,
    response_model=InviteOut,
    responses=errors(400, 401, 403, 404, 413, 422),
)
def post_invite(
    body: InviteCreate, request: Request, session: SessionDep, _: OperatorDep
) -> InviteOut:
    """A new invite link, for one run or all; it works until it expires, is used up or is
    revoked. With `target_answers`, each labeller it makes is shown `completion_code` (made up
    when left out) once they have given that many answers."""
    invite = create_invite(
        session,
        run_id=body.run_id,
        expires_at=utcnow() + timedelta(days=body.expires_in_days),
        max_uses=body.max_uses,
        target_answers=body.target_answers,
        completion_code=body.completion_code,
        note=body.note,
    )
    return invite_out(request, invite)


@router.get(
    "/api/invites", tags=["invites"], response_model=list[InviteOut], responses=errors(401, 403)
)
def get_invites(request: Request, session: SessionDep, _: OperatorDep) -> list[InviteOut]:
    return [invite_out(request, invite) for invite in list_invites(session)]


@router.post(
    "/api/invites/{invite_id}/revoke",
    tags=["invites"],
    response_model=InviteOut,
    responses=errors(401, 403, 404, 422),
)
def post_revoke(
    invite_id: InviteId, request: Request, session: SessionDep, _: OperatorDep
) -> InviteOut:
    """The link stops admitting anyone at once; labellers who joined by it keep their access
    (revoke them on the labellers list)."""
    return invite_out(request, revoke_invite(session, invite_id=invite_id))


@router.post(
    "/api/join/{code}",
    tags=["invites"],
    status_code=201,
    response_model=JoinedOut,
    responses=errors(
        400, 404, 409, 413, 422,
        also={410: {"model": ErrorOut, "description": "the link was revoked, has expired or "
                    "is used up"}},
    ),
)
def post_join(code: InviteCode, session: SessionDep, body: JoinRequest | None = None) -> JoinedOut:
    """Join by an invite link: a new labeller and its bearer token (shown this once). No token
    needed: the link is the permission. 404 for an unknown link; 410 when it was revoked, has
    expired or is used up."""
    joined = join_invite(session, code=code, participant=body.participant if body else None)
    return JoinedOut(
        labeller_id=joined.labeller.id,
        name=joined.labeller.name,
        token=joined.token,
        run_id=joined.invite.run_id,
        target_answers=joined.invite.target_answers,
    )


@router.get(
    "/api/label/progress",
    tags=["label"],
    response_model=ProgressOut,
    responses=errors(401, 403),
)
def get_progress(session: SessionDep, caller: LabellerDep) -> ProgressOut:
    """The caller's answers so far; for a labeller invited with a target, the completion code
    once the target is reached (null before)."""
    assert caller.labeller_id is not None
    progress = labeller_progress(session, labeller_id=caller.labeller_id)
    return ProgressOut(
        labels=progress.labels,
        target_answers=progress.target_answers,
        completion_code=progress.completion_code,
        run_id=progress.run_id,
    )


@router.get("/join/{code}", response_class=HTMLResponse, include_in_schema=False)
def join_page(code: str, request: Request, session: SessionDep) -> HTMLResponse:
    """The invite link itself: a how-to page that joins, or a page that says why it cannot."""
    invite = read_invite(session, code=code) if len(code) <= 64 else None
    if invite is None:
        return closed_page(request, "This invite link is not known: check that it was copied "
                                    "whole, or ask the study's organisers for a new one.", 404)
    state = invite_state(invite)
    if state != "open":
        return closed_page(request, CLOSED_TEXT[state] + " Ask the study's organisers for a "
                                                          "new link.", 410)
    instruction = None
    if invite.run_id is not None:
        try:
            run = services.get_run(session, run_id=invite.run_id)
            instruction = run_instruction(run.task, run.instruction)
        except NotFound:
            instruction = None
    return page(request, "join.html", nav="label", code=code, run_id=invite.run_id,
                instruction=instruction, target=invite.target_answers)


def closed_page(request: Request, message: str, status_code: int) -> HTMLResponse:
    response = page(request, "join_closed.html", nav="label", message=message)
    response.status_code = status_code
    return response

"""Invite links: operators make, list, revoke them and check completion codes; whoever opens
one joins as a labeller.

`/join/<code>` is a page: an open link shows the run's instruction, a short how-to and the
study's consent text (if any); the page's script joins (`POST /api/join/<code>`; with a consent
text, only once the person agrees), keeps the new labeller's token in the browser and offers
the label page. A link that no longer admits anyone answers a page that says why (410: revoked,
expired, used up, or its run is over), an unknown one a page that says so (404): never a stack
trace. Links are made with the server's `public_url` when it is set.
"""

from __future__ import annotations

from datetime import timedelta
from typing import Annotated

from fastapi import APIRouter, Path, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse

from crowdstudy.completion import Progress, labeller_progress, verify_code
from crowdstudy.invites import (
    CLOSED_TEXT,
    ENTRY_TEST_WAIT,
    create_invite,
    entry_test_missing,
    invite_runs_open,
    invite_state,
    join_invite,
    list_invites,
    read_invite,
    revoke_invite,
    waits_on_entry_test,
)
from labelqueue import Invite, NotFound
from labelqueue.entry_test import EntryPassInvalid
from labelqueue.models import utcnow
from labelqueue.waiting import finish_if_waited
from runviews.activity import labeller_waiting
from runvocab.instructions import run_instruction
from server import services
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.routes.pages import page
from server.schemas import INT32_MAX, ErrorOut, RunFilter, errors
from server.study_schemas import (
    InviteCreate,
    InviteOut,
    JoinedOut,
    JoinRequest,
    ProgressOut,
    StatusOut,
    VerifiedOut,
    VerifyRequest,
    WaitingOut,
)

router = APIRouter()

InviteId = Annotated[int, Path(ge=1, le=INT32_MAX, description="the invite's id")]
InviteCode = Annotated[str, Path(max_length=64, description="the code in the invite link")]


def invite_url(request: Request, invite: Invite) -> str:
    """The link to hand out: under the server's `public_url` when set, else at the address the
    operator's request came to."""
    public_url = request.app.state.settings.public_url
    if public_url is not None:
        return f"{public_url}/join/{invite.code}"
    return str(request.url_for("join_page", code=invite.code))


def invite_outs(request: Request, session: SessionDep, invites: list[Invite]) -> list[InviteOut]:
    runs_open = invite_runs_open(session, invites)
    return [
        InviteOut(**{column: getattr(invite, column) for column in InviteOut.model_fields
                     if column not in ("url", "state", "entry_test_missing")},
                  url=invite_url(request, invite),
                  state=invite_state(invite, runs_open=runs_open[invite.id]),
                  entry_test_missing=entry_test_missing(session, invite))
        for invite in invites
    ]


def invite_out(request: Request, session: SessionDep, invite: Invite) -> InviteOut:
    return invite_outs(request, session, [invite])[0]


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
    """A new invite link, for one run or all; it works until it expires, is used up, is revoked
    or its run is over. Each participant's study ends with their own completion code (prefixed
    with `completion_code`, checked with `POST /api/invites/verify`) once they give
    `target_answers` decisive answers on the run, the run is over, or check pairs pause them;
    then they are sent to `redirect_url` if it is set. An `entry_pass` that does not fit the
    run's practice pairs is a 422 located at it."""
    try:
        invite = _create(body, session)
    except EntryPassInvalid as err:
        raise RequestValidationError([{"type": "value_error", "loc": ("body", "entry_pass"),
                                       "msg": str(err)}]) from None
    return invite_out(request, session, invite)


def _create(body: InviteCreate, session: SessionDep) -> Invite:
    return create_invite(
        session,
        run_id=body.run_id,
        expires_at=utcnow() + timedelta(days=body.expires_in_days),
        max_uses=body.max_uses,
        target_answers=body.target_answers,
        completion_code=body.completion_code,
        note=body.note,
        redirect_url=body.redirect_url,
        consent_text=body.consent_text,
        pause_message=body.pause_message,
        wait_limit_s=body.wait_limit_s,
        entry_pass=body.entry_pass,
    )


@router.get(
    "/api/invites", tags=["invites"], response_model=list[InviteOut], responses=errors(401, 403)
)
def get_invites(request: Request, session: SessionDep, _: OperatorDep) -> list[InviteOut]:
    return invite_outs(request, session, list_invites(session))


@router.post(
    "/api/invites/verify",
    tags=["invites"],
    response_model=VerifiedOut,
    responses=errors(400, 401, 403, 404, 413, 422),
)
def post_verify(body: VerifyRequest, session: SessionDep, _: OperatorDep) -> VerifiedOut:
    """Whose completion code this is, and how far they got: decisive answers on the invite's
    run against its target, whether (and why) their study is complete, and whether the code is
    earned (`earned`: pay them, as the participants list's `code_valid`). 404 for a code that
    is no participant's (a typo, or made up). The study-code prefix may be left out; case and
    spaces or dashes between its characters do not matter."""
    verified = verify_code(session, body.code)
    if verified is None:
        raise NotFound("no participant has this completion code: check it was copied whole")
    return VerifiedOut(**vars(verified))


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
    return invite_out(request, session, revoke_invite(session, invite_id=invite_id))


@router.post(
    "/api/join/{code}",
    tags=["invites"],
    status_code=201,
    response_model=JoinedOut,
    responses=errors(
        400, 403, 404, 409, 413, 422, 429,
        also={410: {"model": ErrorOut, "description": "the link was revoked, has expired or "
                    "is used up"}},
    ),
)
def post_join(code: InviteCode, request: Request, session: SessionDep,
              body: JoinRequest | None = None) -> JoinedOut:
    """Join by an invite link: a new labeller and its bearer token (shown this once). No token
    needed: the link is the permission. A participant id that joined the link before gets its
    labeller back with a new token, and takes no use (`rejoined`). 404 for an unknown link;
    410 when it was revoked, has expired or is used up; 403 for a participant whose labeller
    was revoked; 429 (with `Retry-After`) when the link is joined too fast."""
    request.app.state.join_limit.check(code, "this invite link")
    joined = join_invite(session, code=code, participant=body.participant if body else None,
                         consent=body.consent if body else False)
    if joined.rejoined:  # the old token stops in this process at once (others: the cache's s)
        request.app.state.token_cache.forget(joined.labeller.id)
    return JoinedOut(
        labeller_id=joined.labeller.id,
        name=joined.labeller.name,
        token=joined.token,
        run_id=joined.invite.run_id,
        target_answers=joined.invite.target_answers,
        rejoined=joined.rejoined,
    )


@router.get(
    "/api/label/progress",
    tags=["label"],
    response_model=ProgressOut,
    responses=errors(401, 403),
)
def get_progress(session: SessionDep, caller: LabellerDep) -> ProgressOut:
    """The caller's answers so far; for a labeller who joined by an invite, where their study
    stands and, once it is complete, their own completion code (null before)."""
    assert caller.labeller_id is not None
    return progress_out(labeller_progress(session, labeller_id=caller.labeller_id))


def progress_out(progress: Progress) -> ProgressOut:
    return ProgressOut(**vars(progress))


@router.get(
    "/api/label/status",
    tags=["label"],
    response_model=StatusOut,
    responses=errors(401, 403, 422),
)
def get_status(session: SessionDep, caller: LabellerDep, run_id: RunFilter = None) -> StatusOut:
    """What the label page shows when it has no pair: the caller's progress and, unless their
    study is complete, why nothing is there (the run waits for a worker, pretrains, explores or
    trains, with an estimate; the round's pairs are with others; no run is open). For one who
    joined by an invite for one run, that run is asked about whatever `run_id` says. One whose
    invite's entry test no open run has the practice pairs for waits on that (`entry_test`),
    not on the runs. A participant who has asked for pairs and got none for the invite's
    `wait_limit_s` is done: complete, `why` "nothing_left", with their code."""
    assert caller.labeller_id is not None
    finish_if_waited(session, labeller_id=caller.labeller_id)  # nobody waits unpaid
    progress = labeller_progress(session, labeller_id=caller.labeller_id)
    waiting = None
    if not progress.complete and progress.entry_pass is not None and waits_on_entry_test(
            session, labeller_id=caller.labeller_id):
        waiting = WaitingOut(reason="entry_test", text=ENTRY_TEST_WAIT, run_id=None, eta_s=None)
    elif not progress.complete:
        scope = progress.run_id if progress.run_id is not None else run_id
        why = labeller_waiting(session, run_id=scope)
        waiting = WaitingOut(reason=why.reason, text=why.text, run_id=why.run_id,
                             eta_s=why.eta_s)
    return StatusOut(progress=progress_out(progress), waiting=waiting)


@router.get("/join/{code}", response_class=HTMLResponse, include_in_schema=False)
def join_page(code: str, request: Request, session: SessionDep) -> HTMLResponse:
    """The invite link itself: a how-to page that joins, or a page that says why it cannot."""
    invite = read_invite(session, code=code)  # None too for what no code can be (a NUL)
    if invite is None:
        return closed_page(request, "This invite link is not known: check that it was copied "
                                    "whole, or ask the study's organisers for a new one.", 404)
    state = invite_state(invite, runs_open=invite_runs_open(session, [invite])[invite.id])
    if state == "closed":
        return closed_page(request, CLOSED_TEXT[state] + " Thank you for your interest: "
                           "there is nothing left to do here.", 410, code=code,
                           title="This study has ended")
    if state != "open":
        return closed_page(request, CLOSED_TEXT[state] + " Ask the study's organisers for a "
                                                          "new link.", 410, code=code)
    instruction = None
    if invite.run_id is not None:
        try:
            run = services.get_run(session, run_id=invite.run_id)
            instruction = run_instruction(run.task, run.instruction)
        except NotFound:
            instruction = None
    return page(request, "join.html", nav="label", code=code, run_id=invite.run_id,
                instruction=instruction, target=invite.target_answers,
                consent=invite.consent_text, redirect=invite.redirect_url is not None)


def closed_page(request: Request, message: str, status_code: int, code: str | None = None,
                title: str = "This link cannot be used") -> HTMLResponse:
    response = page(request, "join_closed.html", nav="label", message=message, code=code,
                    title=title)
    response.status_code = status_code
    return response

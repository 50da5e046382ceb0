"""Labeller endpoints: lease the next query, answer it, fetch its clips."""

from __future__ import annotations

import time
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse

from labelqueue import LabelSource, submit_label
from server import clips, services
from server.deps import LabellerDep, SessionDep, SettingsDep, bearer_token, caller_from_token
from server.schemas import LabelOut, LabelSubmit, NextQuery

router = APIRouter(prefix="/api", tags=["label"])


@router.get(
    "/label/next",
    response_model=NextQuery,
    responses={204: {"description": "nothing to label now; poll again"}},
)
def next_query(
    session: SessionDep,
    settings: SettingsDep,
    caller: LabellerDep,
    run_id: int | None = None,
    ahead_of: int | None = None,
) -> NextQuery | Response:
    """Lease the next query. `ahead_of=<query_id being shown>` keeps that lease and leases one
    more, so the page can preload the next pair."""
    assert caller.labeller_id is not None
    query = services.next_query(
        session,
        settings=settings,
        labeller_id=caller.labeller_id,
        run_id=run_id,
        ahead_of=ahead_of,
    )
    return Response(status_code=204) if query is None else query


@router.post(
    "/label/{query_id}",
    status_code=201,
    response_model=LabelOut,
    responses={200: {"model": LabelOut, "description": "a repeat: the label already stored"}},
)
def post_label(
    query_id: int, body: LabelSubmit, session: SessionDep, caller: LabellerDep, response: Response
) -> LabelOut:
    assert caller.labeller_id is not None
    label, created = submit_label(
        session,
        query_id=query_id,
        labeller_id=caller.labeller_id,
        choice=body.choice,
        left_is_first=body.left_is_first,
        shown_at=body.shown_at,
        source=LabelSource.HUMAN,
    )
    if not created:
        response.status_code = 200
    return LabelOut.model_validate(label)


@router.get(
    "/clips/{query_id}/{side}",
    response_class=FileResponse,
    responses={200: {"content": {"video/mp4": {}}}},
)
def get_clip(
    query_id: int,
    side: str,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    expires: Annotated[int | None, Query()] = None,
    sig: Annotated[str | None, Query(max_length=128)] = None,
) -> FileResponse:
    """An mp4 clip (Range requests supported); a signed URL from next-query, or a bearer token."""
    if expires is not None or sig is not None:
        valid = (
            expires is not None
            and sig is not None
            and clips.signature_is_valid(
                settings=settings,
                query_id=query_id,
                side=side,
                expires=expires,
                sig=sig,
                now=time.time(),
            )
        )
        if not valid:
            raise HTTPException(403, "clip URL signature is invalid or has expired")
    else:
        caller_from_token(session=session, settings=settings, token=bearer_token(request))
    path = services.clip_path(session, settings=settings, query_id=query_id, side=side)
    return FileResponse(path, media_type="video/mp4")

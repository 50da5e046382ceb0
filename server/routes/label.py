"""Labeller endpoints: lease the next query, answer it, fetch its clips.

Next and submit are the label API's hot path, on `hot_router`: `LeanRoute`s (documented like any
route, served without FastAPI's per-request dependency solver), each an `async def` with one
cheap async dependency (`LabellerCallDep`) that serves its queue work (`LabellerCall.serve`), and
answers with JSON bytes serialised once by pydantic: FastAPI does not validate the returned model
again. The declared `response_model` still documents the body in OpenAPI.
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel

from server import clips, services
from server.deps import (
    BEARER_SECURITY,
    LabellerCallDep,
    SessionDep,
    SettingsDep,
    bearer_token,
    caller_from_token,
)
from server.lean_route import LeanRoute
from server.schemas import (
    AheadOf,
    Expires,
    LabelOut,
    LabelSubmit,
    NextQuery,
    QueryId,
    RunFilter,
    errors,
)

router = APIRouter(prefix="/api", tags=["label"])
hot_router = APIRouter(prefix="/api", tags=["label"], route_class=LeanRoute)


def json_response(body: BaseModel, status_code: int = 200) -> Response:
    """`body` as JSON, serialised once (as FastAPI would, without validating it again)."""
    return Response(body.model_dump_json(), status_code, media_type="application/json")


BEARER_OR_SIGNED: dict[str, Any] = {"security": [{}, {"bearer": []}]}
"""a clip URL's signature (`expires`, `sig`) or a bearer token"""


@hot_router.get(
    "/label/next",
    response_model=NextQuery,
    responses=errors(
        401, 403, 404, 409, 422, also={204: {"description": "nothing to label now; poll again"}}
    ),
    openapi_extra=BEARER_SECURITY,
)
async def next_query(
    call: LabellerCallDep, run_id: RunFilter = None, ahead_of: AheadOf = None
) -> Response:
    """Lease the next query. `ahead_of=<query_id being shown>` keeps that lease and leases one
    more, so the page can preload the next pair."""
    query = await call.serve(services.next_query, run_id=run_id, ahead_of=ahead_of)
    return Response(status_code=204) if query is None else json_response(query)


@hot_router.post(
    "/label/{query_id:int}",
    status_code=201,
    response_model=LabelOut,
    responses=errors(
        400, 401, 403, 404, 409, 413, 422,
        also={200: {"model": LabelOut, "description": "a repeat: the label already stored"}},
    ),
    openapi_extra=BEARER_SECURITY,
)
async def post_label(query_id: QueryId, body: LabelSubmit, call: LabellerCallDep) -> Response:
    """Answer a leased query. A revoked labeller: 403; a run no longer running or paused, an
    expired lease or another labeller's query: 409; a `left_is_first` other than next-query's:
    422. `shown_at` is stored within [the lease's start, now]."""
    out, created = await call.serve(services.answer_out, query_id=query_id, body=body)
    return json_response(out, status_code=201 if created else 200)


@router.get(
    "/clips/{query_id:int}/{side}",
    response_class=FileResponse,
    responses=errors(
        401, 403, 404, 422,
        also={
            200: {"content": {"video/mp4": {}}},
            206: {"description": "the byte range asked for", "content": {"video/mp4": {}}},
        },
    ),
    openapi_extra=BEARER_OR_SIGNED,
)
def get_clip(
    query_id: QueryId,
    side: str,
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    expires: Expires = None,
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

"""Labeller endpoints: lease the next query, answer it, fetch its clips.

Next and submit are the label API's hot path. They are served as plain Starlette routes
(`hot_routes`): each reads its caller with one async call (`get_labeller_call`), checks its query
string, path and body with pydantic (`server.validation`: FastAPI's refusals, without its
per-request dependency solver), and answers with JSON bytes serialised once by pydantic. Their
OpenAPI operations come from `documented`: FastAPI routes of the same endpoints, declared with
the same models, that the app documents and never serves (`server.app`).
"""

from __future__ import annotations

import time
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse
from pydantic import BaseModel, TypeAdapter
from starlette.routing import Route

from server import clips, services
from server.deps import (
    BEARER_SECURITY,
    LabellerCall,
    LabellerCallDep,
    SessionDep,
    SettingsDep,
    bearer_token,
    caller_from_token,
    get_labeller_call,
)
from server.label_schemas import LabelOut, LabelSubmit, NextQuery
from server.schemas import AheadOf, Expires, QueryId, RunFilter, errors
from server.validation import check, check_body, check_query, json_body, refuse_if

router = APIRouter(prefix="/api", tags=["label"])
documented = APIRouter(prefix="/api", tags=["label"])
"""next and submit as OpenAPI describes them; `hot_routes` serve them"""


def json_response(body: BaseModel, status_code: int = 200) -> Response:
    """`body` as JSON, serialised once (as FastAPI would, without validating it again)."""
    return Response(body.model_dump_json(), status_code, media_type="application/json")


BEARER_OR_SIGNED: dict[str, Any] = {"security": [{}, {"bearer": []}]}
"""a clip URL's signature (`expires`, `sig`) or a bearer token"""


class NextParams(BaseModel):
    """next-query's query string"""

    run_id: RunFilter = None
    ahead_of: AheadOf = None


@documented.get(
    "/label/next",
    response_model=NextQuery,
    responses=errors(
        401, 403, 404, 409, 422, 429,
        also={204: {"description": "nothing to label now; poll again"}}
    ),
    openapi_extra=BEARER_SECURITY,
)
async def next_query(call: LabellerCallDep, params: Annotated[NextParams, Query()]) -> Response:
    """Lease the next query. `ahead_of=<query_id being shown>` keeps that lease and leases one
    more, so the page can preload the next pair."""
    query = await call.serve(services.next_query, run_id=params.run_id, ahead_of=params.ahead_of)
    return Response(status_code=204) if query is None else json_response(query)


@documented.post(
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


NEXT_PARAMS = TypeAdapter(NextParams)
QUERY_ID: TypeAdapter[int] = TypeAdapter(QueryId)
LABEL_SUBMIT = TypeAdapter(LabelSubmit)


async def serve_next_query(request: Request) -> Response:
    # FastAPI's order: the caller (401/403) first, then the parameters (422).
    call: LabellerCall = await get_labeller_call(request)
    params, problems = check_query(NEXT_PARAMS, request)
    refuse_if(problems)
    request.app.state.lease_limit.check(call.labeller_id, f"labeller {call.labeller_id}")
    return await next_query(call, params)


async def serve_post_label(request: Request) -> Response:
    # FastAPI's order: a body that is not JSON first, then the caller, then every other refusal.
    body = await json_body(request)
    call: LabellerCall = await get_labeller_call(request)
    query_id, problems = check(QUERY_ID, request.path_params["query_id"], "path", "query_id")
    submit, body_problems = check_body(LABEL_SUBMIT, body)
    refuse_if(problems + body_problems)
    return await post_label(query_id, submit, call)


def _only(method: str, route: Route) -> Route:
    # Starlette adds HEAD to a GET route; a lease is not a HEAD request's business.
    route.methods = {method}
    return route


hot_routes = [
    _only("GET", Route("/api/label/next", serve_next_query, methods=["GET"],
                       name="next_query")),
    _only("POST", Route("/api/label/{query_id:int}", serve_post_label, methods=["POST"],
                        name="post_label")),
]
"""next and submit as the app serves them: plain Starlette routes"""


@router.get(
    "/clips/{query_id:int}/{side}",
    response_class=FileResponse,
    responses=errors(
        401, 403, 404, 422,
        also={
            200: {"content": {"video/mp4": {}, "video/webm": {}}},
            206: {"description": "the byte range asked for",
                  "content": {"video/mp4": {}, "video/webm": {}}},
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
    # An external run's client may upload WebM; every other clip is an h264 mp4.
    return FileResponse(path, media_type="video/webm" if path.suffix == ".webm" else "video/mp4")

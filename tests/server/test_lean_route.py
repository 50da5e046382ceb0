"""`LeanRoute` answers as FastAPI's own route does: one endpoint is served both ways, and every
request, good or bad, gets the same status and body from both; its OpenAPI operation is the
same; endpoints outside its limits are refused when the route is made."""

from __future__ import annotations

from typing import Annotated, Any

import pytest
from fastapi import APIRouter, Depends, FastAPI, Header, HTTPException, Request, Response
from fastapi.testclient import TestClient
from pydantic import BaseModel, ConfigDict

from server.lean_route import LeanRoute
from server.schemas import AheadOf, QueryId, RunFilter, UTCTime


class Answer(BaseModel):
    model_config = ConfigDict(extra="forbid")
    choice: str
    left_is_first: bool | None = None
    shown_at: UTCTime


async def caller(request: Request) -> str:
    token = request.headers.get("authorization", "")
    if token != "Bearer good":
        raise HTTPException(401, "missing or invalid bearer token")
    return token


Caller = Annotated[str, Depends(caller)]


async def next_pair(who: Caller, run_id: RunFilter = None, ahead_of: AheadOf = None) -> Response:
    return Response(f"{who} {run_id} {ahead_of}", media_type="text/plain")


async def answer(query_id: QueryId, body: Answer, who: Caller) -> Response:
    return Response(f"{who} {query_id} {body.model_dump_json()}", 201, media_type="text/plain")


def app_with(route_class: type) -> FastAPI:
    router = APIRouter(prefix="/api", route_class=route_class)
    router.get("/next")(next_pair)
    router.post("/answer/{query_id:int}", status_code=201)(answer)
    app = FastAPI()
    app.include_router(router)
    return app


GOOD = {"Authorization": "Bearer good"}
SHOWN = "2026-11-25T12:00:00Z"
REQUESTS: list[tuple[str, str, dict[str, Any]]] = [
    ("GET", "/api/next", {}),
    ("GET", "/api/next?run_id=3&ahead_of=9", {}),
    ("GET", "/api/next?run_id=0", {}),
    ("GET", "/api/next?run_id=abc&ahead_of=-1", {}),
    ("GET", "/api/next?run_id=99999999999", {}),
    ("GET", "/api/next?run_id=2&run_id=5&other=1", {}),
    ("GET", "/api/next?run_id=", {}),
    ("POST", "/api/answer/5", {"json": {"choice": "left", "shown_at": SHOWN}}),
    ("POST", "/api/answer/5", {"json": {"choice": "left", "left_is_first": True,
                                        "shown_at": "2026-11-25T12:00:00"}}),
    ("POST", "/api/answer/0", {"json": {"choice": "left", "shown_at": SHOWN}}),
    ("POST", "/api/answer/0", {"json": {"shown_at": "never"}}),
    ("POST", "/api/answer/5", {"json": {"choice": 3, "shown_at": SHOWN, "extra": 1}}),
    ("POST", "/api/answer/5", {"json": [1, 2]}),
    ("POST", "/api/answer/5", {"json": None}),
    ("POST", "/api/answer/5", {}),
    ("POST", "/api/answer/5", {"content": b'{"choice": "left",',
                               "headers": {"Content-Type": "application/json"}}),
    ("POST", "/api/answer/5", {"content": b'{"choice": "\xff"}',
                               "headers": {"Content-Type": "application/json"}}),
    ("POST", "/api/answer/5", {"content": b'{"choice": "left", "shown_at": "' + SHOWN.encode()
                               + b'"}', "headers": {"Content-Type": "text/plain"}}),
    ("POST", "/api/answer/5", {"content": b'{"choice": "left", "shown_at": "' + SHOWN.encode()
                               + b'"}', "headers": {"Content-Type": "application/vnd.x+json"}}),
    ("POST", "/api/answer/5", {"content": b"choice=left",
                               "headers": {"Content-Type": "application/x-www-form-urlencoded"}}),
    ("POST", "/api/answer/5", {"content": b'{"choice": "left"}'}),
    # Nested deeper than JSON decoding goes (about 10 KB, the body limit is 64 KiB): a 400.
    ("POST", "/api/answer/5", {"content": b"[" * 5000 + b"]" * 5000,
                               "headers": {"Content-Type": "application/json"}}),
    ("POST", "/api/answer/5", {"content": b'{"choice": ' + b"[" * 5000 + b"]" * 5000 + b"}",
                               "headers": {"Content-Type": "application/json"}}),
]


@pytest.mark.parametrize(("method", "url", "extra"), REQUESTS)
@pytest.mark.parametrize("token", ["good", "bad"])
def test_the_same_answer_as_fastapis_route(
    method: str, url: str, extra: dict[str, Any], token: str
) -> None:
    extra = dict(extra)
    headers = {"Authorization": f"Bearer {token}", **extra.pop("headers", {})}
    with TestClient(app_with(LeanRoute)) as lean, TestClient(app_with(APIRouter().route_class)) \
            as plain:
        got = lean.request(method, url, headers=headers, **extra)
        want = plain.request(method, url, headers=headers, **extra)
    assert (got.status_code, got.text) == (want.status_code, want.text)


def test_a_good_request_reaches_the_endpoint_with_its_values() -> None:
    with TestClient(app_with(LeanRoute)) as client:
        got = client.get("/api/next?run_id=3&ahead_of=9", headers=GOOD)
        posted = client.post("/api/answer/7", headers=GOOD,
                             json={"choice": "left", "shown_at": "2026-11-25T13:00:00+01:00"})
    assert (got.status_code, got.text) == (200, "Bearer good 3 9")
    assert posted.status_code == 201
    assert posted.text == ('Bearer good 7 {"choice":"left","left_is_first":null,'
                           '"shown_at":"2026-11-25T12:00:00Z"}')


def test_a_body_of_bytes_that_are_not_text_is_a_422_not_a_500() -> None:
    """FastAPI's own route fails to encode such an input in its 422 (a 500)."""
    with TestClient(app_with(LeanRoute)) as client:
        got = client.post("/api/answer/5", headers=GOOD | {"Content-Type": "text/plain"},
                          content=b"\xff\xfe")
    assert got.status_code == 422
    assert got.json()["detail"][0]["loc"] == ["body"]


def test_its_openapi_operations_are_fastapis() -> None:
    assert app_with(LeanRoute).openapi() == app_with(APIRouter().route_class).openapi()


async def with_header(x_token: Annotated[str, Header()]) -> Response:
    return Response()


async def with_deep_dependency(who: Annotated[str, Depends(next_pair)]) -> Response:
    return Response()


def blocking(run_id: RunFilter = None) -> Response:
    return Response()


@pytest.mark.parametrize(
    ("endpoint", "refusal"),
    [
        (with_header, "path and query parameters and one JSON body only"),
        (with_deep_dependency, "only async dependencies of the request alone"),
        (blocking, "an async endpoint"),
    ],
)
def test_endpoints_outside_its_limits_are_refused_when_made(endpoint: Any, refusal: str) -> None:
    router = APIRouter(route_class=LeanRoute)
    with pytest.raises(TypeError, match=refusal):
        router.get("/x")(endpoint)

"""Next and submit, served as plain Starlette routes, answer as FastAPI's own routes of the same
endpoints would: the same app serves each request both ways, on the same database, and every
refusal gets the same status and body; their OpenAPI operations are those FastAPI describes."""

from __future__ import annotations

import itertools
from typing import Any

from fastapi import FastAPI
from fastapi.testclient import TestClient
from server_helpers import OPERATOR_TOKEN, bearer, new_labeller, running_run_with_queries
from sqlalchemy.orm import Session

from server.app import create_app
from server.routes import label
from server.settings import Settings

SHOWN = "2026-11-25T12:00:00Z"
JSON = {"Content-Type": "application/json"}
REQUESTS: list[tuple[str, str, dict[str, Any]]] = [
    ("GET", "/api/label/next", {}),
    ("GET", "/api/label/next?run_id=1&ahead_of=9", {}),
    ("GET", "/api/label/next?run_id=0", {}),
    ("GET", "/api/label/next?run_id=abc&ahead_of=-1", {}),
    ("GET", "/api/label/next?run_id=99999999999", {}),
    ("GET", "/api/label/next?run_id=2&run_id=1&other=1", {}),
    ("GET", "/api/label/next?run_id=", {}),
    ("POST", "/api/label/0", {"json": {"choice": "left", "shown_at": SHOWN}}),
    ("POST", "/api/label/0", {"json": {"shown_at": "never"}}),
    ("POST", "/api/label/99999999999", {"json": {"choice": "left", "shown_at": SHOWN}}),
    ("POST", "/api/label/5", {"json": {"choice": 3, "shown_at": SHOWN, "extra": 1}}),
    ("POST", "/api/label/5", {"json": {"choice": "left", "shown_at": SHOWN, "flag": "odd"}}),
    ("POST", "/api/label/5", {"json": [1, 2]}),
    ("POST", "/api/label/5", {"json": None}),
    ("POST", "/api/label/5", {}),
    ("POST", "/api/label/5", {"content": b'{"choice": "left",', "headers": JSON}),
    ("POST", "/api/label/5", {"content": b'{"choice": "\xff"}', "headers": JSON}),
    ("POST", "/api/label/5", {"content": b'{"choice": "left", "shown_at": "' + SHOWN.encode()
                              + b'"}', "headers": {"Content-Type": "text/plain"}}),
    ("POST", "/api/label/5", {"content": b"choice=left",
                              "headers": {"Content-Type": "application/x-www-form-urlencoded"}}),
    ("POST", "/api/label/5", {"content": b'{"choice": "left"}'}),
    # Nested deeper than JSON decoding goes: a 400, from both.
    ("POST", "/api/label/5", {"content": b"[" * 5000 + b"]" * 5000, "headers": JSON}),
    ("POST", "/api/label/5", {"content": b'{"choice": ' + b"[" * 5000 + b"]" * 5000 + b"}",
                              "headers": JSON}),
]


def served_by_fastapi(settings: Settings) -> FastAPI:
    """The app with next and submit served by FastAPI's own routes of the same endpoints."""
    app = create_app(settings)
    app.router.routes[:] = [r for r in app.router.routes if r not in label.hot_routes]
    app.include_router(label.documented)
    del app.openapi  # FastAPI's own document, of the routes it serves
    return app


def test_every_request_gets_fastapis_answer(
    client: TestClient, session: Session, settings: Settings
) -> None:
    running_run_with_queries(client, session, settings, n=2)
    tokens = {"labeller": new_labeller(client, "alice"), "operator": OPERATOR_TOKEN,
              "nobody": "not-a-token"}
    differ = []
    with TestClient(served_by_fastapi(settings)) as fastapi_served:
        for (method, url, extra), who in itertools.product(REQUESTS, tokens):
            extra = dict(extra)
            headers = bearer(tokens[who]) | extra.pop("headers", {})
            want = fastapi_served.request(method, url, headers=headers, **extra)
            got = client.request(method, url, headers=headers, **extra)
            if want.status_code < 300:  # a lease renewed on the second ask: the same query
                same = got.status_code == want.status_code and \
                    got.json()["query_id"] == want.json()["query_id"]
            else:
                same = (got.status_code, got.json()) == (want.status_code, want.json())
            if not same:
                differ.append((method, url, who, got.status_code, got.text[:300],
                               want.status_code, want.text[:300]))
    assert not differ


def test_a_good_request_leases_and_answers_through_the_plain_routes(
    client: TestClient, session: Session, settings: Settings,
) -> None:
    run_id, ids = running_run_with_queries(client, session, settings, n=2)
    alice = bearer(new_labeller(client, "alice"))
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=alice).json()
    ahead = client.get(f"/api/label/next?run_id={run_id}&ahead_of={shown['query_id']}",
                       headers=alice).json()
    assert [shown["query_id"], ahead["query_id"]] == ids
    answer = {"choice": "left", "left_is_first": shown["left_is_first"], "shown_at": SHOWN}
    posted = client.post(f"/api/label/{shown['query_id']}", json=answer, headers=alice)
    again = client.post(f"/api/label/{shown['query_id']}", json=answer, headers=alice)
    assert (posted.status_code, again.status_code) == (201, 200)
    assert posted.json()["answer"] == ("first" if shown["left_is_first"] else "second")
    assert again.json()["id"] == posted.json()["id"]


def test_a_body_of_bytes_that_are_not_text_is_a_422_naming_the_body(client: TestClient) -> None:
    """FastAPI's own route cannot encode such an input in its 422."""
    alice = bearer(new_labeller(client, "alice"))
    got = client.post("/api/label/5", headers=alice | {"Content-Type": "text/plain"},
                      content=b"\xff\xfe")
    assert got.status_code == 422
    assert got.json()["detail"][0]["loc"] == ["body"]


def test_head_is_not_a_lease(client: TestClient) -> None:
    alice = bearer(new_labeller(client, "alice"))
    response = client.head("/api/label/next", headers=alice)
    assert response.status_code == 405 and response.headers["allow"] == "GET"


def test_their_openapi_operations_are_fastapis(settings: Settings) -> None:
    served = create_app(settings).openapi()
    fastapi_served = served_by_fastapi(settings).openapi()
    assert served == fastapi_served
    assert set(served["paths"]["/api/label/next"]) == {"get"}
    assert [p["name"] for p in served["paths"]["/api/label/next"]["get"]["parameters"]] == [
        "run_id", "ahead_of"]
    assert served["paths"]["/api/label/{query_id}"]["post"]["requestBody"]["content"][
        "application/json"]["schema"] == {"$ref": "#/components/schemas/LabelSubmit"}

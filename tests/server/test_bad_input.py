"""Whatever a client sends, the answer is a clear 4xx: out-of-range numbers, oversized or too
deeply nested bodies, methods a path does not take; and every response carries the security
headers."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run, snapshot
from sqlalchemy.orm import Session

from server.app import create_app
from server.middleware import JSON_DEPTH_LIMIT, nests_deeper_than
from server.settings import Settings

HUGE = 18446744073709551616  # 2**64: beyond every integer column
TOO_BIG_FOR_INTEGER = 2**31  # beyond PostgreSQL's INTEGER, the ids' and budgets' column type


def _detail_names(response: httpx.Response, name: str) -> bool:
    detail = response.json()["detail"]
    return any(name in error["loc"] for error in detail) if isinstance(detail, list) else False


@pytest.mark.parametrize("number", [HUGE, TOO_BIG_FOR_INTEGER, -HUGE])
def test_out_of_range_integers_are_a_422_naming_the_parameter(
    client: TestClient, session: Session, number: int
) -> None:
    labeller = bearer(new_labeller(client, "alice"))
    run = new_run(client)
    before = snapshot(session)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 1}
    label = {"choice": "left", "left_is_first": True, "shown_at": "2026-01-01T00:00:00Z"}
    cases: list[tuple[str, str, dict[str, Any], str]] = [
        ("GET", f"/api/label/next?run_id={number}", {"headers": labeller}, "run_id"),
        ("GET", f"/api/label/next?ahead_of={number}", {"headers": labeller}, "ahead_of"),
        ("GET", f"/api/runs/{number}", {"headers": OPERATOR}, "run_id"),
        ("GET", f"/api/runs/{number}/throughput", {"headers": OPERATOR}, "run_id"),
        ("GET", f"/api/runs/{run['id']}/metrics?after_step={number}", {"headers": OPERATOR},
         "after_step"),
        ("POST", f"/api/runs/{number}/pause", {"headers": OPERATOR}, "run_id"),
        ("GET", f"/api/export?run_id={number}", {"headers": OPERATOR}, "run_id"),
        ("POST", "/api/runs", {"headers": OPERATOR, "json": body | {"budget": number}}, "budget"),
        ("POST", "/api/runs", {"headers": OPERATOR, "json": body | {"seed": number}}, "seed"),
        ("PATCH", f"/api/labellers/{number}", {"headers": OPERATOR, "json": {"active": False}},
         "labeller_id"),
    ]
    if number > 0:  # a negative id does not match these routes at all (404)
        cases.append(("POST", f"/api/label/{number}", {"headers": labeller, "json": label},
                      "query_id"))
        cases.append(("GET", f"/api/clips/{number}/first?expires=1&sig=00", {}, "query_id"))
    if abs(number) == HUGE:  # a clip URL's expiry is unix seconds: int64
        cases.append(("GET", f"/api/clips/1/first?expires={number}&sig=00", {}, "expires"))
    for method, url, kwargs, name in cases:
        response = client.request(method, url, **kwargs)
        assert response.status_code == 422, (url, response.text)
        assert _detail_names(response, name), (url, response.text)
    assert snapshot(session) == before


@pytest.mark.parametrize("number", ["NaN", "Infinity", "-Infinity"])
def test_a_number_json_has_no_form_for_is_a_422_not_a_500(
    client: TestClient, session: Session, number: str
) -> None:
    """Python's JSON reads NaN and Infinity: refused, the 422 gives them back as text."""
    labeller = bearer(new_labeller(client, "alice"))
    before = snapshot(session)
    json_type = {"content-type": "application/json"}
    for url, headers, body, name in [
        ("/api/runs", OPERATOR, '{"task": "dmc:cheetah_run", "algo": "sac", "budget": %s}',
         "budget"),
        ("/api/runs/external", OPERATOR, '{"task": "t", "budget": 5, "gold_rate": %s}',
         "gold_rate"),
        ("/api/label/1", labeller, '{"choice": "left", "left_is_first": %s}', "left_is_first"),
    ]:
        response = client.post(url, content=body % number, headers=headers | json_type)
        assert response.status_code == 422, (url, response.text)
        assert _detail_names(response, name), (url, response.text)
    assert snapshot(session) == before


@contextmanager
def served(settings: Settings) -> Iterator[httpx.Client]:
    """The app behind uvicorn on a free port, and a keep-alive client of it: a real socket."""
    config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=0, log_level="error")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 20
        while not server.started:
            assert time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.05)
        port = server.servers[0].sockets[0].getsockname()[1]
        with httpx.Client(base_url=f"http://127.0.0.1:{port}") as http:
            yield http
    finally:
        server.should_exit = True
        thread.join(timeout=20)


def test_an_out_of_range_number_does_not_drop_the_connection(settings: Settings) -> None:
    """Over a real socket: the next request on the same keep-alive connection still works."""
    with served(settings) as http:
        bad = http.get(f"/api/runs/{HUGE}", headers=OPERATOR)
        assert bad.status_code == 422
        assert http.get("/api/runs", headers=OPERATOR).status_code == 200
        assert bad.headers.get("connection") != "close"


def test_a_body_over_the_limit_is_a_413_and_nothing_is_stored(
    client: TestClient, session: Session
) -> None:
    before = snapshot(session)
    config = {"note": "x" * (80 * 1024)}
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 1, "config": config}
    response = client.post("/api/runs", json=body, headers=OPERATOR)
    assert response.status_code == 413
    assert "65536 bytes" in response.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as it streams in
        yield b'{"task": "dmc:cheetah_run", "algo": "sac", "budget": 1, "name": "'
        for _ in range(100):
            yield b"y" * 1024
        yield b'"}'

    headers = OPERATOR | {"Content-Type": "application/json"}
    streamed = client.post("/api/runs", content=chunks(), headers=headers)
    assert streamed.status_code == 413 and "65536 bytes" in streamed.json()["detail"]
    assert snapshot(session) == before


def test_a_run_config_over_16_kib_is_refused_so_the_dashboard_stays_small(
    client: TestClient, session: Session
) -> None:
    before = snapshot(session)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 1}
    for field in ("config", "teacher_params"):
        big = {f"key{i}": "v" * 100 for i in range(200)}  # about 22 KiB as JSON
        response = client.post("/api/runs", json=body | {field: big}, headers=OPERATOR)
        assert response.status_code == 422, response.text
        assert _detail_names(response, field) and "16384" in response.text
    assert snapshot(session) == before
    assert client.post("/api/runs", json=body | {"config": {"sac.lr": 1e-4}},
                       headers=OPERATOR).status_code == 201


def test_a_method_a_path_does_not_take_is_a_405_listing_those_it_does(
    client: TestClient,
) -> None:
    labeller = bearer(new_labeller(client, "alice"))
    options = client.options("/api/runs", headers=OPERATOR)
    assert options.status_code == 405 and options.headers["allow"] == "GET, POST"
    for path in ("/api/label/count", "/api/label/next"):
        response = client.post(path, json={}, headers=labeller)
        assert response.status_code == 405, response.text
        assert response.headers["allow"] == "GET"
    put = client.put("/api/labellers/1", json={}, headers=OPERATOR)
    assert put.status_code == 405 and put.headers["allow"] == "PATCH"


@pytest.mark.parametrize("path", ["/", "/label", "/runs", "/runs/1", "/api/runs", "/healthz",
                                  "/static/api.js", "/nothing-here"])
def test_every_response_forbids_framing_and_sniffing(client: TestClient, path: str) -> None:
    response = client.get(path)
    assert response.headers["x-frame-options"] == "DENY"
    assert "frame-ancestors 'none'" in response.headers["content-security-policy"]
    assert response.headers["x-content-type-options"] == "nosniff"
    assert response.headers["referrer-policy"] == "same-origin"


def _nested(depth: int, shape: str) -> bytes:
    """JSON nested `depth` levels deep: lists, or objects whose one key holds the next level."""
    if shape == "list":
        return b"[" * depth + b"]" * depth
    return b'{"a":' * depth + b"1" + b"}" * depth


# Either side of the limit; around the depth where Python's JSON decoding would give up (its
# recursion limit, less the stack in use), where a body decoded but could not be echoed back in
# a 422 before the limit; 5000 levels (10 KB) is what the audit sent.
DEPTHS = [1, 30, JSON_DEPTH_LIMIT - 1, JSON_DEPTH_LIMIT, JSON_DEPTH_LIMIT + 1, 900, 950, 5000]


@pytest.mark.parametrize(("body", "deeper"), [
    (b"[]", False),
    (b"[" * 64 + b"]" * 64, False),
    (b"[" * 65 + b"]" * 65, True),
    (b'{"a":' * 65 + b"1" + b"}" * 65, True),
    (b"[" * 65, True),  # unclosed: deep all the same
    # Brackets inside strings are text, however many; escaped quotes do not end a string.
    (b'{"a": "' + b"[" * 100 + b'"}', False),
    (b'{"a": "\\\\"' + b", " + b"[" * 65 + b"]" * 65 + b"}", True),
    (b'{"a": "\\\\\\"' + b"[" * 100 + b'"}', False),
    (b'["\\u005b' + b"{" * 70 + b'"]', False),
])
def test_nesting_depth_counts_arrays_and_objects_outside_strings(body: bytes,
                                                                 deeper: bool) -> None:
    assert nests_deeper_than(body, 64) is deeper


def test_a_body_nested_deeper_than_the_limit_is_a_400_that_names_it(client: TestClient,
                                                                    session: Session) -> None:
    before = snapshot(session)
    config = b'{"a":' * (JSON_DEPTH_LIMIT - 1) + b"1" + b"}" * (JSON_DEPTH_LIMIT - 1)
    body = b'{"task": "dmc:cheetah_run", "algo": "sac", "budget": 1, "config": %s}'
    json_type = {"Content-Type": "application/json"}

    def chunks(content: bytes) -> Iterator[bytes]:  # no Content-Length: it streams in parts
        yield from (content[i : i + 7] for i in range(0, len(content), 7))

    # 64 levels with the body's own: decoded, and refused by the route for what it says.
    at_limit = client.post("/api/runs", content=body % config, headers=OPERATOR | json_type)
    assert at_limit.status_code == 422, at_limit.text
    assert "unknown config field 'a'" in at_limit.text
    deeper = body % (b"[" + config + b"]")
    # FastAPI decodes a body without a type as JSON, and an application/*+json one.
    for content, content_type in [(deeper, json_type), (chunks(deeper), json_type), (deeper, {}),
                                  (deeper, {"Content-Type": "application/merge-patch+json"})]:
        refused = client.post("/api/runs", content=content, headers=OPERATOR | content_type)
        assert refused.status_code == 400, refused.text
        assert refused.json() == {
            "detail": f"request body nests JSON deeper than {JSON_DEPTH_LIMIT} levels, the most "
                      "accepted"}
    # Not JSON by its type: the body's model refuses it as it refuses any text.
    text = client.post("/api/runs", content=deeper, headers=OPERATOR | {"Content-Type":
                                                                        "text/plain"})
    assert text.status_code == 422
    assert snapshot(session) == before


def test_no_body_however_deeply_nested_is_a_500(client: TestClient, session: Session) -> None:
    """Fuzz every operation that takes a body with deeply nested JSON, bare and in each of its
    body's fields: each answer is a 4xx (400, or the 401/403/404/409/422 the operation gives
    anyway), never a 500, and nothing is stored."""
    labeller = bearer(new_labeller(client, "alice"))
    new_run(client)
    before = snapshot(session)
    paths = client.get("/openapi.json").json()["paths"]
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    operations = []
    for path, item in paths.items():
        for method, operation in item.items():
            body = operation.get("requestBody", {}).get("content", {}).get("application/json")
            if body is None:
                continue
            ref = body["schema"].get("$ref") or next(
                (s["$ref"] for s in body["schema"].get("anyOf", []) if "$ref" in s), None)
            fields = list(schemas[ref.split("/")[-1]]["properties"]) if ref else []
            url = path.replace("{code}", "x").replace("{", "").replace("}", "")
            url = "/".join("1" if part.endswith("_id") else part for part in url.split("/"))
            operations.append((method.upper(), url, fields))
    assert {(m, u) for m, u, _ in operations} >= {("POST", "/api/label/1"),
                                                  ("POST", "/api/runs")}
    statuses = set()
    for method, url, fields in operations:
        headers = (labeller if url.startswith("/api/label") else OPERATOR) | {
            "Content-Type": "application/json"}
        for depth in DEPTHS:
            for shape in ("list", "object"):
                inner = _nested(depth, shape)
                bodies = [inner] + [b'{"%s": %s}' % (f.encode(), inner) for f in fields]
                for content in bodies:
                    response = client.request(method, url, content=content, headers=headers)
                    assert response.status_code < 500, (method, url, depth, content[:40])
                    statuses.add(response.status_code)
    assert snapshot(session) == before
    assert {400, 422} <= statuses


def test_a_deeply_nested_label_does_not_drop_the_connection(settings: Settings) -> None:
    """Over a real socket, as the audit sent it: 10 KB of nested brackets to /api/label/{id} is
    a 400, and the keep-alive connection serves the next request."""
    with served(settings) as http:
        created = http.post("/api/labellers", json={"name": "alice"}, headers=OPERATOR)
        labeller = bearer(created.json()["token"])
        for depth in (5000, 950):
            bad = http.post("/api/label/1", content=_nested(depth, "list"),
                            headers=labeller | {"Content-Type": "application/json"})
            assert bad.status_code == 400, (depth, bad.text[:200])
            assert bad.headers.get("connection") != "close"
        assert http.get("/api/label/next", headers=labeller).status_code == 204


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-le", "utf-32", "utf-32-be"])
def test_a_deep_body_in_utf16_or_utf32_is_a_400_too(client: TestClient, encoding: str) -> None:
    deep = ("[" * 5000 + "]" * 5000).encode(encoding)
    assert nests_deeper_than(deep, JSON_DEPTH_LIMIT)
    refused = client.post("/api/label/1", content=deep, headers=OPERATOR | {
        "Content-Type": "application/json"})
    assert refused.status_code == 400, refused.text
    shallow = '{"choice": "left"}'.encode(encoding)
    assert not nests_deeper_than(shallow, JSON_DEPTH_LIMIT)


def test_blank_names_notes_and_consent_texts_are_a_422_naming_the_field(
    client: TestClient,
) -> None:
    blank = " \t\u3000\n "
    new_labeller(client, "ann")
    [ann] = client.get("/api/labellers", headers=OPERATOR).json()
    refused = [
        ("POST", "/api/labellers", {"name": blank}, "name"),
        ("PATCH", f"/api/labellers/{ann['id']}", {"name": "   "}, "name"),
        ("POST", "/api/runs", {"task": "dmc:cheetah_run", "algo": "pebble", "name": blank},
         "name"),
        ("POST", "/api/runs/external", {"task": blank, "budget": 5}, "task"),
        ("POST", "/api/runs/external", {"task": "gym:Hopper-v5", "budget": 5, "name": blank},
         "name"),
        ("POST", "/api/invites", {"note": "  "}, "note"),
        # A consent text of spaces would let people join without agreeing to anything.
        ("POST", "/api/invites", {"consent_text": blank}, "consent_text"),
        ("POST", "/api/invites", {"pause_message": blank}, "pause_message"),
    ]
    for method, path, body, field in refused:
        response = client.request(method, path, json=body, headers=OPERATOR)
        assert response.status_code == 422, (path, body, response.text)
        [problem] = response.json()["detail"]
        assert problem["loc"] == ["body", field] and "blank" in problem["msg"], problem
    assert [who["name"] for who in client.get("/api/labellers", headers=OPERATOR).json()] == [
        "ann"]
    assert client.get("/api/invites", headers=OPERATOR).json() == []
    assert client.get("/api/runs/external", headers=OPERATOR).json() == []
    # Text with something in it is stored without its outer white space.
    made = client.post("/api/labellers", json={"name": "  bob "}, headers=OPERATOR).json()
    renamed = client.patch(f"/api/labellers/{ann['id']}", json={"name": "\tann-2 "},
                           headers=OPERATOR).json()
    study = client.post("/api/invites", headers=OPERATOR, json={
        "note": " pilot ", "consent_text": "\n We keep your answers. \n"}).json()
    assert (made["name"], renamed["name"], study["note"], study["consent_text"]) == (
        "bob", "ann-2", "pilot", "We keep your answers.")

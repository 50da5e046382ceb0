"""Explicit pydantic validation for the label API's plain Starlette routes (`routes/label.py`).

A request's parts are checked with pydantic and refused in FastAPI's terms, so a client cannot
tell these routes from FastAPI's own: a 422 `RequestValidationError` whose `loc` starts with
"query", "path" or "body" (every refusal of a request together), and a 400 for a body that is
not UTF-8 text (a body nested too deeply never gets here: `middleware.JSON_DEPTH_LIMIT`).
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import HTTPException, Request
from fastapi.exceptions import RequestValidationError
from pydantic import TypeAdapter, ValidationError

from server.middleware import is_json_content_type

Problems = list[dict[str, Any]]


def check(adapter: TypeAdapter[Any], value: Any, *where: str) -> tuple[Any, Problems]:
    """`value` validated by `adapter` (as FastAPI validates, from attributes too) and no
    refusals, or None and the refusals, each `loc` under `where`."""
    try:
        return adapter.validate_python(value, from_attributes=True), []
    except ValidationError as error:
        return None, [{**e, "loc": (*where, *e["loc"])} for e in error.errors(include_url=False)]


def check_query(adapter: TypeAdapter[Any], request: Request) -> tuple[Any, Problems]:
    """The query string as the model `adapter` validates it (the last of repeated names)."""
    return check(adapter, dict(request.query_params), "query")


async def json_body(request: Request) -> Any:
    """The body, read before anything else is checked: decoded JSON for a JSON content type
    (422 at once when it is not JSON), else the bytes (refused by the body's model); None when
    there is none."""
    raw = await request.body()
    if not raw:
        return None
    if not is_json_content_type(request.headers.get("content-type", "")):
        return raw
    try:
        return json.loads(raw)
    except json.JSONDecodeError as error:
        raise RequestValidationError([{
            "type": "json_invalid", "loc": ("body", error.pos),
            "msg": "JSON decode error", "input": {}, "ctx": {"error": error.msg},
        }]) from None
    except ValueError:  # not UTF-8 text
        raise HTTPException(400, "There was an error parsing the body") from None


def check_body(adapter: TypeAdapter[Any], value: Any) -> tuple[Any, Problems]:
    """The decoded body (`json_body`) as `adapter` validates it; a missing body is refused."""
    if value is None:
        return None, [{"type": "missing", "loc": ("body",), "msg": "Field required",
                       "input": None}]
    parsed, problems = check(adapter, value, "body")
    for problem in problems:  # bytes that are not text must still go back as JSON
        if isinstance(problem.get("input"), bytes):
            problem["input"] = problem["input"].decode(errors="replace")
    return parsed, problems


def refuse_if(problems: Problems) -> None:
    """A 422 with every refusal of the request, if there is any."""
    if problems:
        raise RequestValidationError(problems)

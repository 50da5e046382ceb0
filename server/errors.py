"""One place that turns refusals into JSON client errors `{"detail": "..."}`: the queue's errors,
a configuration no worker could run, numbers the database cannot hold, and 405s that name every
method the path allows. Any other exception is a fault of the server's (a 500), never a refusal
of the request's: a route that refuses input raises `labelqueue.Invalid`."""

from __future__ import annotations

import math
import re
from collections.abc import Awaitable, Callable, Iterable, Iterator
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from sqlalchemy.exc import DataError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import BaseRoute

from crowdstudy.invites import InviteClosed
from labelqueue import (
    Conflict,
    EntryFailed,
    Invalid,
    LeaseError,
    NotFound,
    OtherRun,
    Paused,
    Revoked,
    StaleToken,
)
from runvocab.names import ConfigError

STATUS_OF: dict[type[Exception], int] = {
    NotFound: 404,
    Revoked: 403,
    Paused: 403,
    EntryFailed: 403,
    OtherRun: 403,
    LeaseError: 409,
    Conflict: 409,  # InvalidTransition and RunClosed too: they are Conflicts
    InviteClosed: 410,
    Invalid: 422,  # DatasetError too
    ConfigError: 422,
}
OUT_OF_RANGE = "a number in the request is out of the range the database holds"


def _handler(status_code: int) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    async def handle(_request: Request, error: Exception) -> JSONResponse:
        return JSONResponse(status_code=status_code, content={"detail": str(error)})

    return handle


async def _stale_token(_request: Request, error: Exception) -> JSONResponse:
    # As for any token that names no labeller: the caller must sign in with the new one.
    return JSONResponse(status_code=401, content={"detail": f"invalid or revoked bearer token "
                        f"({error})"}, headers={"WWW-Authenticate": "Bearer"})


async def _out_of_range(_request: Request, _error: Exception) -> JSONResponse:
    # A safety net: the schemas bound every number, so this is for one that slipped through.
    return JSONResponse(status_code=422, content={"detail": OUT_OF_RANGE})


def _routes(routes: Iterable[BaseRoute]) -> Iterator[BaseRoute]:
    """The app's routes, with those of included routers in place of the routers."""
    for route in routes:
        included = getattr(route, "original_router", None)
        yield from _routes(included.routes) if included is not None else (route,)


def allowed_methods(request: Request) -> set[str]:
    """Every method the app's routes take at this request's path (the router's own 405 names
    only the methods of the first route whose path matched)."""
    path = request.url.path
    allowed: set[str] = set()
    for route in _routes(request.app.router.routes):
        regex: re.Pattern[str] | None = getattr(route, "path_regex", None)
        methods: set[str] | None = getattr(route, "methods", None)
        if regex is not None and methods and regex.match(path):
            allowed |= methods
    return allowed


def _json_safe(value: Any) -> Any:
    """`value` with each number JSON has no form for (NaN, an infinity) as its text, and each
    lone surrogate in a string (JSON's "\\ud800" escape, which no UTF-8 encodes) as its
    escape."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, str):
        return value.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(value, dict):
        return {_json_safe(key): _json_safe(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_json_safe(item) for item in value]
    return value


async def _invalid_request(_request: Request, error: Exception) -> JSONResponse:
    # FastAPI's own 422, but a NaN or an infinity the body held (Python's JSON reads them) goes
    # back as text, and a lone surrogate as its escape: rendering either would fail (a 500).
    assert isinstance(error, RequestValidationError)
    return JSONResponse(status_code=422,
                        content={"detail": _json_safe(jsonable_encoder(error.errors()))})


async def _http_error(request: Request, error: Exception) -> JSONResponse:
    assert isinstance(error, StarletteHTTPException)
    headers = dict(error.headers or {})
    if error.status_code == 405:
        given = {m.strip() for m in headers.get("Allow", "").split(",") if m.strip()}
        headers["Allow"] = ", ".join(sorted(given | allowed_methods(request)))
    return JSONResponse(
        status_code=error.status_code, content={"detail": error.detail}, headers=headers or None
    )


def install_error_handlers(app: FastAPI) -> None:
    """Register the mappings above on `app` (once, in the app factory)."""
    for error_type, status_code in STATUS_OF.items():
        app.add_exception_handler(error_type, _handler(status_code))
    app.add_exception_handler(StaleToken, _stale_token)
    app.add_exception_handler(OverflowError, _out_of_range)
    app.add_exception_handler(DataError, _out_of_range)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _invalid_request)

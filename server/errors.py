"""One place that turns the queue's refusals into JSON client errors `{"detail": "..."}`."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from labelqueue import Conflict, LeaseError, NotFound

STATUS_OF: dict[type[Exception], int] = {
    NotFound: 404,
    LeaseError: 409,
    Conflict: 409,  # InvalidTransition too: it is a Conflict
    ValueError: 422,
}


def _handler(status_code: int) -> Callable[[Request, Exception], Awaitable[JSONResponse]]:
    async def handle(_request: Request, error: Exception) -> JSONResponse:
        return JSONResponse(status_code=status_code, content={"detail": str(error)})

    return handle


def install_error_handlers(app: FastAPI) -> None:
    """Register the mapping above on `app` (once, in the app factory)."""
    for error_type, status_code in STATUS_OF.items():
        app.add_exception_handler(error_type, _handler(status_code))

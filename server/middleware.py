"""ASGI middleware: a request-body limit (413) and security headers on every response."""

from __future__ import annotations

import json

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

BODY_LIMIT_BYTES = 64 * 1024
"""the largest request body the API reads; a run's config is far smaller"""
SECURITY_HEADERS = {
    # No page of the app may be framed (clickjacking on the label page's buttons).
    "x-frame-options": "DENY",
    "content-security-policy": "frame-ancestors 'none'",
    "x-content-type-options": "nosniff",
    # Tokens travel in the URL fragment, which no Referer carries; send only the origin anyway.
    "referrer-policy": "same-origin",
}


_SECURITY_PAIRS = [(name.encode(), value.encode()) for name, value in SECURITY_HEADERS.items()]


def too_large_detail(limit: int) -> str:
    return f"request body is larger than {limit} bytes ({limit // 1024} KiB), the most accepted"


def _too_large(limit: int) -> tuple[Message, Message]:
    body = json.dumps({"detail": too_large_detail(limit)}).encode()
    start: Message = {
        "type": "http.response.start",
        "status": 413,
        "headers": [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
        ],
    }
    return start, {"type": "http.response.body", "body": body}


class HardeningMiddleware:
    """Refuses bodies over `limit` bytes with 413 (by Content-Length, or while a chunked body
    streams in) before any route reads them; adds `SECURITY_HEADERS` to every response."""

    def __init__(self, app: ASGIApp, limit: int = BODY_LIMIT_BYTES) -> None:
        self.app = app
        self.limit = limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", ()))
                present = {k.lower() for k, _ in headers}
                headers += [pair for pair in _SECURITY_PAIRS if pair[0] not in present]
                message = {**message, "headers": headers}
            await send(message)

        declared = next((v for k, v in scope["headers"] if k == b"content-length"), None)
        if declared is not None and (not declared.isdigit() or int(declared) > self.limit):
            for message in _too_large(self.limit):
                await send_with_headers(message)
            return
        received = 0

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.limit:  # a chunked body: the app's error handler says 413
                    raise HTTPException(413, too_large_detail(self.limit))
            return message

        await self.app(scope, limited_receive, send_with_headers)

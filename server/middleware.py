"""ASGI middleware: request-body limits (413 over a size, 400 over a JSON nesting depth) and
security headers on every response."""

from __future__ import annotations

import json
import re

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

BODY_LIMIT_BYTES = 64 * 1024
"""the largest request body the API reads; a run's config is far smaller"""
JSON_DEPTH_LIMIT = 64
"""the deepest JSON body the API decodes; its own bodies nest 3 levels. Deeper ones are refused
before decoding, so no body comes near the interpreter's recursion limit (some 900 levels,
where decoding, validating or echoing it back would fail depending on the stack in use)."""
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


_ESCAPE = re.compile(rb"\\.", re.DOTALL)
_NOT_STRUCTURE = bytes(b for b in range(256) if b not in b'[]{}"')


def is_json_content_type(content_type: str) -> bool:
    """Whether a body of this type is JSON: application/json or application/*+json."""
    kind = content_type.partition(";")[0].strip().lower()
    return kind == "application/json" or (
        kind.startswith("application/") and kind.endswith("+json")
    )


def nests_deeper_than(body: bytes, limit: int) -> bool:
    """Whether `body`, read as JSON, opens more than `limit` arrays or objects inside each
    other. Brackets inside strings do not count; malformed JSON is left to the decoder. A body
    in UTF-16 or UTF-32, which `json.loads` decodes by itself, is scanned as the decoder reads
    it."""
    encoding = json.detect_encoding(body)
    if encoding != "utf-8":
        body = body.decode(encoding, errors="replace").encode()
    if body.count(b"[") + body.count(b"{") <= limit:
        return False  # the common case, at C speed: too few brackets to nest that deep
    depth, in_string = 0, False
    # Escaped characters go first, so a quote that remains opens or closes a string.
    for byte in _ESCAPE.sub(b"", body).translate(None, _NOT_STRUCTURE):
        if byte == 0x22:  # "
            in_string = not in_string
        elif in_string:
            continue
        elif byte in b"[{":
            depth += 1
            if depth > limit:
                return True
        else:
            depth -= 1
    return False


def too_deep_detail(limit: int) -> str:
    return f"request body nests JSON deeper than {limit} levels, the most accepted"


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
    streams in) and JSON bodies nested deeper than `JSON_DEPTH_LIMIT` with 400, before any
    route decodes them; adds `SECURITY_HEADERS` to every response."""

    def __init__(self, app: ASGIApp, limit: int = BODY_LIMIT_BYTES,
                 uploads: tuple[re.Pattern[str], int] | None = None) -> None:
        self.app = app
        self.default_limit = limit
        self.uploads = uploads
        """the paths that take uploads (an external run's clips), and their larger limit"""

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

        limit = self.default_limit
        if self.uploads is not None and self.uploads[0].match(scope["path"]):
            limit = self.uploads[1]
        declared = next((v for k, v in scope["headers"] if k == b"content-length"), None)
        if declared is not None and (not declared.isdigit() or int(declared) > limit):
            for message in _too_large(limit):
                await send_with_headers(message)
            return
        # FastAPI decodes a body without a content type as JSON too.
        content_type = next((v for k, v in scope["headers"] if k == b"content-type"), b"")
        check_depth = not content_type or is_json_content_type(content_type.decode("latin-1"))
        received, chunks = 0, []

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                body = message.get("body", b"")
                received += len(body)
                # Raised here, the app's error handler answers (a chunked body's 413 too).
                if received > limit:
                    raise HTTPException(413, too_large_detail(limit))
                if check_depth:
                    chunks.append(body)
                    if (not message.get("more_body", False)
                            and nests_deeper_than(b"".join(chunks), JSON_DEPTH_LIMIT)):
                        raise HTTPException(400, too_deep_detail(JSON_DEPTH_LIMIT))
            return message

        await self.app(scope, limited_receive, send_with_headers)

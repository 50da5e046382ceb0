"""Clip URLs and clip files.

Browsers' <video> tags cannot send an Authorization header, so the next-query response carries
signed clip URLs: `/api/clips/{query_id}/{side}?expires=<unix s>&sig=<hex>`, where `sig` is the
HMAC-SHA256 of `"{query_id}:{side}:{expires}"` under the settings' `secret_key`. The URL works
until `expires` (`clip_url_seconds` after it was issued) for whoever holds it; a bearer token
works too. A clip's file is found only from the query's stored key under the clips folder: no
client-supplied path reaches the filesystem, and a key that escapes the folder is refused.
"""

from __future__ import annotations

import hashlib
import hmac
from pathlib import Path

from labelqueue import Query
from server.settings import Settings

SIDES = ("first", "second")


def signature(*, secret: str, query_id: int, side: str, expires: int) -> str:
    message = f"{query_id}:{side}:{expires}".encode()
    return hmac.new(secret.encode(), message, hashlib.sha256).hexdigest()


def signed_clip_url(*, settings: Settings, query_id: int, side: str, now: float) -> str:
    """A URL for one clip, valid for `clip_url_seconds` from `now` (unix seconds)."""
    expires = int(now + settings.clip_url_seconds)
    sig = signature(secret=settings.secret_key, query_id=query_id, side=side, expires=expires)
    return settings.public(f"/api/clips/{query_id}/{side}?expires={expires}&sig={sig}")


def signature_is_valid(
    *, settings: Settings, query_id: int, side: str, expires: int, sig: str, now: float
) -> bool:
    if expires < now:
        return False
    expected = signature(secret=settings.secret_key, query_id=query_id, side=side, expires=expires)
    # As bytes: compare_digest refuses str with non-ASCII characters, which a URL can hold.
    return hmac.compare_digest(expected.encode(), sig.encode("utf-8", "surrogatepass"))


def left_is_first(*, settings: Settings, query_id: int, labeller_id: int) -> bool:
    """Which segment a labeller sees on the left: unpredictable, but stable across reloads."""
    message = f"order:{query_id}:{labeller_id}".encode()
    return hmac.new(settings.secret_key.encode(), message, hashlib.sha256).digest()[0] & 1 == 1


def clip_file(*, settings: Settings, query: Query, side: str) -> Path | None:
    """The file of a query's clip, or None: unknown side, not rendered, outside the folder."""
    if side not in SIDES:
        return None
    key = query.first_clip if side == "first" else query.second_clip
    if not key or key.startswith(("/", "\\")) or "\\" in key or ":" in key:
        return None
    root = settings.clips_root
    path = (root / key).resolve()
    if not path.is_relative_to(root) or not path.is_file():
        return None
    return path

"""Pairs as an external run's server takes them (`sepoa.client`): a clip's bytes and content
type, a pair's body and its idempotency key, and pushes that fit the server's limits."""

from __future__ import annotations

import hashlib
import io
import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

Clip = np.ndarray | str | os.PathLike[str] | bytes
"""a frame array (uint8, (frames, height, width, 3)), an .mp4/.webm/.npy file, or its bytes"""
MEDIA = {".mp4": "video/mp4", ".webm": "video/webm", ".npy": "application/x-npy"}
PUSH_PAIRS = 500
"""the most pairs one push takes (the server's limit)"""
PUSH_BYTES = 60 * 1024
"""the most one push's body holds: the server reads 64 KiB by default
(`SEPOA_BODY_LIMIT_BYTES`); a push it still finds too large (413) is split in two"""


@dataclass(frozen=True)
class Pair:
    """Two clips to compare, and what the client knows of them (hidden from labellers)."""

    first: Clip
    second: Clip
    key: str | None = None
    """the idempotency key; None: one made from the pair's content"""
    gold: Literal["first", "second"] | None = None
    """a gold pair's known answer: it measures labellers and costs no budget"""
    returns: tuple[float, float] | None = None
    """the two segments' true returns, for accuracy and the calibration report"""
    trajectory_returns: tuple[float, float] | None = None
    meta: Mapping[str, Any] | None = None
    """the client's own ids, given back with the pair's answers"""


def clip_body(clip: Clip) -> tuple[bytes, str]:
    """A clip's bytes and content type."""
    if isinstance(clip, np.ndarray):
        buffer = io.BytesIO()
        np.save(buffer, np.ascontiguousarray(clip, dtype=np.uint8) if clip.dtype != np.uint8
                else clip)
        return buffer.getvalue(), MEDIA[".npy"]
    if isinstance(clip, bytes):
        return clip, "video/webm" if clip[:4] == b"\x1a\x45\xdf\xa3" else "video/mp4"
    path = Path(clip)
    if path.suffix.lower() not in MEDIA:
        raise ValueError(f"{path}: a clip file is .mp4, .webm or .npy")
    return path.read_bytes(), MEDIA[path.suffix.lower()]


def pair_body(pair: Pair, first: str, second: str) -> dict[str, Any]:
    """A pair as the server takes it, with its clips' ids and its key."""
    body: dict[str, Any] = {"first_clip": first, "second_clip": second, "gold": pair.gold,
                            "returns": pair.returns, "trajectory_returns": pair.trajectory_returns,
                            "meta": None if pair.meta is None else dict(pair.meta)}
    content = json.dumps(body, sort_keys=True, separators=(",", ":"))
    key = pair.key or "auto-" + hashlib.sha256(content.encode()).hexdigest()[:40]
    return {"key": key, **{name: value for name, value in body.items() if value is not None}}


def push_batches(bodies: Sequence[dict[str, Any]]) -> list[list[dict[str, Any]]]:
    """The pairs' bodies in order, in pushes of at most `PUSH_PAIRS` pairs and `PUSH_BYTES`
    bytes (one pair larger than that is a push of its own)."""
    batches: list[list[dict[str, Any]]] = []
    batch: list[dict[str, Any]] = []
    size = 0
    for body in bodies:
        item = len(compact(body)) + 1
        if batch and (len(batch) == PUSH_PAIRS or size + item > PUSH_BYTES):
            batches.append(batch)
            batch, size = [], 0
        batch.append(body)
        size += item
    return [*batches, batch] if batch else batches


def compact(value: Any) -> bytes:
    return json.dumps(value, separators=(",", ":")).encode()

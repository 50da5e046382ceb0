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
MAGIC = {b"\x1a\x45\xdf\xa3": "video/webm", b"\x93NUMPY": "application/x-npy"}
"""the first bytes of a WebM file and of a .npy file (an MP4's are no fixed ones)"""
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
    """the client's own ids, given back with the pair's answers (NumPy numbers and arrays
    are sent as plain ones)"""


def frames_npy(frames: np.ndarray) -> bytes:
    """A frame array as the .npy file the server encodes. Integer frames all within 0-255 are
    taken as uint8; ValueError for any others (float frames in [0, 1] would be black)."""
    if frames.dtype != np.uint8:
        fits = np.issubdtype(frames.dtype, np.integer) and (
            frames.size == 0 or (frames.min() >= 0 and frames.max() <= 255))
        if not fits:
            raise ValueError(f"frames are {frames.dtype}: a clip's frames are uint8 (0-255); "
                             "make float frames in [0, 1] so with "
                             "(frames * 255).round().astype(np.uint8)")
        frames = frames.astype(np.uint8)
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(frames))
    return buffer.getvalue()


def clip_body(clip: Clip) -> tuple[bytes, str]:
    """A clip's bytes and content type; a file's bytes are told apart by their first bytes."""
    if isinstance(clip, np.ndarray):
        return frames_npy(clip), MEDIA[".npy"]
    if isinstance(clip, bytes):
        kind = next((kind for magic, kind in MAGIC.items() if clip.startswith(magic)), None)
        return clip, kind or MEDIA[".mp4"]
    path = Path(clip)
    if path.suffix.lower() not in MEDIA:
        raise ValueError(f"{path}: a clip file is .mp4, .webm or .npy")
    return path.read_bytes(), MEDIA[path.suffix.lower()]


def plain(value: Any) -> Any:
    """`value` with each NumPy number or array as the Python one JSON writes (RL code's
    returns and ids are often NumPy's, which json.dumps refuses)."""
    def default(item: Any) -> Any:
        if isinstance(item, np.generic | np.ndarray):
            return item.tolist()
        raise TypeError(f"a {type(item).__name__} has no form in JSON")
    return None if value is None else json.loads(json.dumps(value, default=default))


def pair_body(pair: Pair, first: str, second: str) -> dict[str, Any]:
    """A pair as the server takes it, with its clips' ids and its key."""
    body: dict[str, Any] = {"first_clip": first, "second_clip": second, "gold": pair.gold,
                            "returns": plain(pair.returns),
                            "trajectory_returns": plain(pair.trajectory_returns),
                            "meta": None if pair.meta is None else plain(dict(pair.meta))}
    content = json.dumps(body, sort_keys=True, separators=(",", ":"))
    key = pair.key or "auto-" + hashlib.sha256(content.encode()).hexdigest()[:40]
    return {"key": key, **{name: value for name, value in body.items() if value is not None}}


def each_once(bodies: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The pairs' bodies in order, each the first time it comes: a pair asked twice in one
    ask is one query, as when asked again later (one push may not name a key twice)."""
    return list({compact(body): body for body in bodies}.values())


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

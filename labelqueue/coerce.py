"""Plain values for the database: NumPy scalars to Python numbers, NaN to null, safe clip keys."""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from pathlib import PurePosixPath
from typing import Any

from labelqueue.errors import Invalid


def finite(value: Any) -> float | None:
    """A float, or None for None, NaN and infinities (neither JSON nor SQLite keeps NaN)."""
    return None if value is None or not math.isfinite(value) else float(value)


def json_value(value: Any) -> Any:
    """`value` as strict JSON takes it (PostgreSQL refuses NaN; NumPy scalars are not JSON)."""
    if value is None or isinstance(value, bool | str):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return finite(value)
    if isinstance(value, Mapping):
        return json_object(value)
    if isinstance(value, list | tuple):
        return [json_value(item) for item in value]
    return value


def json_object(values: Mapping[str, Any]) -> dict[str, Any]:
    return {str(key): json_value(value) for key, value in values.items()}


def clip_key(key: str | None) -> str | None:
    """`key` if it is a relative name inside the clips folder; Invalid otherwise.

    Clips are stored by key, never by a path a client chose, so a key must not escape the folder.
    """
    if key is None:
        return None
    parts = PurePosixPath(key).parts
    if not parts or key.startswith("/") or "\\" in key or ":" in key or ".." in parts:
        raise Invalid(f"clip key {key!r} is not a relative name inside the clips folder")
    return key

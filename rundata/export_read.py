"""Reading a label export back (JSONL, CSV or Parquet; docs/EXPORT.md) as row dicts.

Values come back with the export's types whatever the format: int, float, bool, str, a list
of floats for a skill, and None for null; timestamps stay ISO 8601 strings. Columns this
version does not declare are kept (CSV cells as text). Every problem with the file is an
`ExportFileError`, one line that says what is wrong.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Callable
from typing import Any

from labelqueue.export import COLUMNS
from rundata.label_files import FORMATS

_SUFFIXES = {".jsonl": "jsonl", ".ndjson": "jsonl", ".csv": "csv", ".parquet": "parquet"}
_PARQUET_MAGIC = b"PAR1"


class ExportFileError(ValueError):
    """A file that cannot be read as a label export."""


def export_format(path: str) -> str:
    """jsonl, csv or parquet: by the file name's suffix, else by the first bytes."""
    suffix = os.path.splitext(path)[1].lower()
    if suffix in _SUFFIXES:
        return _SUFFIXES[suffix]
    with open(path, "rb") as file:
        head = file.read(4096)
    if head.startswith(_PARQUET_MAGIC):
        return "parquet"
    first = head.lstrip().split(b"\n", 1)[0]
    if first.startswith(b"{"):
        return "jsonl"
    if b"label_id" in first and b"," in first:
        return "csv"
    raise ExportFileError(
        f"{path} is not a label export this version reads: name it .jsonl, .csv or .parquet "
        f"({', '.join(FORMATS)}, as `sepoa export` writes them)"
    )


def _bool(text: str) -> bool:
    if text not in ("true", "false"):
        raise ValueError(f"{text!r} is not true or false")
    return text == "true"


_CSV_TYPES: dict[str, Callable[[str], Any]] = {
    "int64": int,
    "float64": float,
    "bool": _bool,
    "string": str,
    "timestamp": str,
    "list<float64>": json.loads,
}
_TYPE_OF = {column.name: (column.type, column.nullable) for column in COLUMNS}


def _csv_value(name: str, text: str) -> Any:
    kind, nullable = _TYPE_OF.get(name, ("string", True))
    if text == "" and (nullable or kind != "string"):
        return None
    return _CSV_TYPES[kind](text)


def _read_csv(path: str) -> tuple[list[str], list[dict[str, Any]]]:
    with open(path, encoding="utf-8", newline="") as file:
        reader = csv.reader(file)
        header = next(reader, None)
        if header is None:
            raise ExportFileError(f"{path} is empty: a CSV export starts with a header row")
        rows = []
        for line, cells in enumerate(reader, start=2):
            if len(cells) != len(header):
                raise ExportFileError(
                    f"{path} line {line}: {len(cells)} cells under a header of {len(header)}"
                )
            try:
                rows.append({name: _csv_value(name, text)
                             for name, text in zip(header, cells, strict=True)})
            except ValueError as error:
                raise ExportFileError(f"{path} line {line}: {error}") from error
    return header, rows


def _read_jsonl(path: str) -> tuple[list[str], list[dict[str, Any]]]:
    rows = []
    with open(path, encoding="utf-8") as file:
        for line, text in enumerate(file, start=1):
            if not text.strip():
                continue
            try:
                row = json.loads(text)
            except json.JSONDecodeError as error:
                raise ExportFileError(f"{path} line {line}: not JSON ({error.msg})") from error
            if not isinstance(row, dict):
                raise ExportFileError(f"{path} line {line}: not a JSON object")
            rows.append(row)
    return list({name: None for row in rows for name in row}), rows


def _read_parquet(path: str) -> tuple[list[str], list[dict[str, Any]]]:
    import pyarrow.parquet as pq  # type: ignore[import-untyped]  # lazily: it is slow to import

    try:
        table = pq.read_table(path)
    except Exception as error:  # pyarrow raises its own ArrowInvalid, OSError, ...
        raise ExportFileError(f"{path}: not a readable Parquet file ({error})") from error
    rows: list[dict[str, Any]] = table.to_pylist()
    for row in rows:  # timestamps as the other formats give them
        for name, value in row.items():
            if hasattr(value, "isoformat"):
                row[name] = value.isoformat(timespec="microseconds")
    return list(table.column_names), rows


_READERS = {"jsonl": _read_jsonl, "csv": _read_csv, "parquet": _read_parquet}


def _from_version_2(row: dict[str, Any]) -> dict[str, Any]:
    """A schema-2 row with its answer as schema 3 names it: `preferred` (null for cant_tell and
    skip, which `choice` then holds) became `answer`."""
    if "answer" in row or "preferred" not in row:
        return row
    return row | {"answer": row["preferred"] or row.get("choice")}


def read_export_table(path: str) -> tuple[list[str], list[dict[str, Any]]]:
    """The columns and the rows of the export file at `path`; the columns are the file's own
    even when it has no rows (a CSV header, a Parquet schema; a JSONL file's keys, so none for
    an empty one). ExportFileError when it cannot be read."""
    if not os.path.exists(path):
        raise ExportFileError(f"{path} does not exist")
    if os.path.isdir(path):
        raise ExportFileError(f"{path} is a folder; give an export file")
    try:
        columns, rows = _READERS[export_format(path)](path)
        if "preferred" in columns and "answer" not in columns:
            columns.append("answer")
        return columns, [_from_version_2(row) for row in rows]
    except UnicodeDecodeError as error:
        raise ExportFileError(f"{path}: not UTF-8 text ({error.reason})") from error
    except OSError as error:
        raise ExportFileError(f"cannot read {path}: {error.strerror or error}") from error


def read_export(path: str) -> list[dict[str, Any]]:
    """The rows of the export file at `path`; ExportFileError when it cannot be read."""
    return read_export_table(path)[1]

"""Label export files: the rows of `labelqueue.export_rows` written as JSONL, CSV or Parquet
(docs/EXPORT.md). `labelqueue.export.SCHEMA_VERSION` is in every row and in the Parquet file's
metadata."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import IO, Any, Literal, get_args

from sqlalchemy.orm import Session

from labelqueue.export import CHUNK_ROWS, COLUMN_NAMES, COLUMNS, SCHEMA_VERSION, export_rows

ExportFormat = Literal["jsonl", "csv", "parquet"]
FORMATS: tuple[ExportFormat, ...] = get_args(ExportFormat)
PARQUET_VERSION_KEY = "sepoa.export.schema_version"
"""the key of the schema version in a Parquet file's key-value metadata"""


def _chunks(rows: Iterator[dict[str, Any]], size: int) -> Iterator[list[dict[str, Any]]]:
    chunk: list[dict[str, Any]] = []
    for row in rows:
        chunk.append(row)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _iso(value: datetime) -> str:
    return value.astimezone(UTC).isoformat(timespec="microseconds")


def _json_value(value: Any) -> Any:
    return _iso(value) if isinstance(value, datetime) else value


def _csv_cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, datetime):
        return _iso(value)
    if isinstance(value, list):
        return json.dumps(value, allow_nan=False)
    return str(value)  # repr-exact for floats


def _write_jsonl(rows: Iterator[dict[str, Any]], out: IO[bytes]) -> int:
    count = 0
    for row in rows:
        line = json.dumps(
            {name: _json_value(value) for name, value in row.items()},
            allow_nan=False,
            ensure_ascii=False,
            separators=(",", ":"),
        )
        out.write(line.encode() + b"\n")
        count += 1
    return count


def _write_csv(rows: Iterator[dict[str, Any]], out: IO[bytes]) -> int:
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(COLUMN_NAMES)
    count = 0
    for chunk in _chunks(rows, CHUNK_ROWS):
        writer.writerows([_csv_cell(value) for value in row.values()] for row in chunk)
        out.write(text.getvalue().encode())
        text.seek(0)
        text.truncate()
        count += len(chunk)
    out.write(text.getvalue().encode())  # the header of an empty export
    return count


def parquet_schema() -> Any:
    """The pyarrow schema of the Parquet export (typed columns even when there are no rows)."""
    import pyarrow as pa  # type: ignore[import-untyped]  # lazily: the server starts fast

    types = {
        "int64": pa.int64(),
        "float64": pa.float64(),
        "string": pa.string(),
        "bool": pa.bool_(),
        "timestamp": pa.timestamp("us", tz="UTC"),
        "list<float64>": pa.list_(pa.float64()),
    }
    fields = [pa.field(column.name, types[column.type], nullable=True) for column in COLUMNS]
    return pa.schema(fields, metadata={PARQUET_VERSION_KEY: str(SCHEMA_VERSION)})


def _write_parquet(rows: Iterator[dict[str, Any]], out: IO[bytes]) -> int:
    import pyarrow as pa
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    schema = parquet_schema()
    count = 0
    with pq.ParquetWriter(out, schema) as writer:
        for chunk in _chunks(rows, CHUNK_ROWS):
            writer.write_table(pa.Table.from_pylist(chunk, schema=schema))
            count += len(chunk)
        if count == 0:
            writer.write_table(schema.empty_table())
    return count


_WRITERS = {"jsonl": _write_jsonl, "csv": _write_csv, "parquet": _write_parquet}


def write_export(
    session: Session, *, fmt: ExportFormat | str, out: IO[bytes], run_id: int | None = None
) -> int:
    """Write the labels (of one run, or all) to `out` as jsonl, csv or parquet; rows written.

    ValueError for an unknown format, NotFound for an unknown run (before anything is written).
    """
    if fmt not in _WRITERS:
        raise ValueError(f"unknown export format {fmt!r}; valid formats: {', '.join(FORMATS)}")
    return _WRITERS[fmt](export_rows(session, run_id=run_id), out)

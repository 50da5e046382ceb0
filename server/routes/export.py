"""Operator endpoint: the label database as a JSONL, CSV or Parquet file (docs/EXPORT.md).

The file is built first, into a spooled temporary file (memory, then disk past a few MB), by
`write_export`, which reads in short transactions of its own; only then is it sent. So an
unknown run is a plain 404 rather than a broken download, and a slow client never keeps a
transaction (on SQLite, the write lock) open.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from typing import IO, Annotated

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse

from labelqueue import EXPORT_SCHEMA_VERSION, ExportFormat, write_export
from server.deps import OperatorDep, SessionDep
from server.schemas import RunFilter, errors

router = APIRouter(prefix="/api", tags=["export"])

MEDIA_TYPES: dict[ExportFormat, str] = {
    "jsonl": "application/x-ndjson",
    "csv": "text/csv",
    "parquet": "application/vnd.apache.parquet",
}
SPOOL_BYTES = 8 * 1024 * 1024
BLOCK_BYTES = 64 * 1024


def export_filename(*, fmt: ExportFormat, run_id: int | None) -> str:
    run = "" if run_id is None else f"-run{run_id}"
    return f"labels{run}-v{EXPORT_SCHEMA_VERSION}.{fmt}"


def _blocks(file: IO[bytes]) -> Iterator[bytes]:
    try:
        file.seek(0)
        while block := file.read(BLOCK_BYTES):
            yield block
    finally:
        file.close()


@router.get(
    "/export",
    response_class=StreamingResponse,
    responses=errors(
        401, 403, 404, 422, also={200: {"content": {media: {} for media in MEDIA_TYPES.values()}}}
    ),
)
def export_labels(
    session: SessionDep,
    _: OperatorDep,
    fmt: Annotated[ExportFormat, Query(alias="format")] = "jsonl",
    run_id: RunFilter = None,
) -> StreamingResponse:
    """Every label (or one run's), one row each, with ground truth: see docs/EXPORT.md."""
    file = tempfile.SpooledTemporaryFile(max_size=SPOOL_BYTES)
    try:
        write_export(session, fmt=fmt, out=file, run_id=run_id)
        size = file.tell()
    except BaseException:
        file.close()
        raise
    filename = export_filename(fmt=fmt, run_id=run_id)
    headers = {
        "Content-Disposition": f'attachment; filename="{filename}"',
        "Content-Length": str(size),
    }
    return StreamingResponse(_blocks(file), media_type=MEDIA_TYPES[fmt], headers=headers)

"""Operator endpoints: the label database as a JSONL, CSV or Parquet file, and a run's episodes
and labels as a Minari dataset in a zip file (docs/EXPORT.md).

The file is built first, into a temporary file on disk, by `write_export` in the export process
(`server.export_job`: a child process at a lower priority, so labellers' requests do not wait
on it), which reads in short read-only transactions; only then is it sent. So an unknown run is
a plain 404 rather than a broken download, and a slow client never keeps a transaction open.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from typing import IO, Annotated, Literal

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import StreamingResponse

from labelqueue import EXPORT_SCHEMA_VERSION, check_database
from rundata.label_files import ExportFormat
from server.deps import OperatorDep, SettingsDep
from server.export_job import ExportProcess
from server.schemas import RunFilter, RunId, errors

router = APIRouter(prefix="/api", tags=["export"])

MEDIA_TYPES: dict[ExportFormat, str] = {
    "jsonl": "application/x-ndjson",
    "csv": "text/csv",
    "parquet": "application/vnd.apache.parquet",
}
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
        401, 403, 404, 422, 503,
        also={200: {"content": {media: {} for media in MEDIA_TYPES.values()}}},
    ),
)
def export_labels(
    request: Request,
    settings: SettingsDep,
    _: OperatorDep,
    fmt: Annotated[ExportFormat, Query(alias="format")] = "jsonl",
    run_id: RunFilter = None,
) -> StreamingResponse:
    """Every label (or one run's), one row each, with ground truth: see docs/EXPORT.md. 503 when
    SQLite's integrity check finds the database damaged: such a file can read back fewer labels
    than it holds, without an error."""
    try:
        check_database(settings.database_url)
    except ValueError as err:
        raise HTTPException(503, str(err)) from None
    export: ExportProcess = request.app.state.export_process
    handle, path = tempfile.mkstemp(prefix="sepoa-export-", suffix=f".{fmt}")
    os.close(handle)
    try:
        export.write(database_url=settings.database_url, fmt=fmt, path=path, run_id=run_id)
        file = open(path, "rb")  # closed by _blocks once sent
    finally:
        os.unlink(path)  # the open file stays readable; nothing is left behind
    filename = export_filename(fmt=fmt, run_id=run_id)
    headers = {
        "Content-Disposition": f'attachment; filename="{filename}"',
        "Content-Length": str(os.fstat(file.fileno()).st_size),
    }
    return StreamingResponse(_blocks(file), media_type=MEDIA_TYPES[fmt], headers=headers)


MINARI_ID_PATTERN = r"^([-_A-Za-z0-9][-_A-Za-z0-9/]*[-_A-Za-z0-9]+/)?[-_A-Za-z0-9]+?-v[0-9]+$"
"""Minari's dataset id (its DATASET_ID_RE) with the version it requires, in ASCII letters,
digits, `-` and `_` (rundata.dataset.check_dataset_id): the id names the zip file in a header,
which is sent in latin-1"""


@router.get(
    "/runs/{run_id}/dataset",
    response_class=StreamingResponse,
    responses=errors(401, 403, 404, 409, 422, also={200: {"content": {"application/zip": {}}}}),
)
def export_dataset(
    request: Request,
    settings: SettingsDep,
    _: OperatorDep,
    run_id: RunId,
    dataset_id: Annotated[str | None, Query(
        max_length=200, pattern=MINARI_ID_PATTERN,
        description="the Minari dataset id, `[namespace/]name-v<version>` in ASCII letters, "
                    "digits, `-`, `_` and `/` (default sepoa/<task>/run-<id>-v0)",
    )] = None,
    data_format: Annotated[Literal["arrow", "hdf5"], Query(
        alias="format", description="Minari's storage: arrow, or hdf5 (which TorchRL reads)",
    )] = "arrow",
) -> StreamingResponse:
    """The run's episodes and labels as a Minari dataset (docs/EXPORT.md), zipped under its
    dataset id: unzip it into a Minari datasets folder. 409 when the run kept no episodes."""
    from rundata.dataset import DatasetError, NoEpisodes

    export: ExportProcess = request.app.state.export_process
    handle, path = tempfile.mkstemp(prefix="sepoa-dataset-", suffix=".zip")
    os.close(handle)
    try:
        written = export.write_dataset(database_url=settings.database_url,
                                       clips_root=str(settings.clips_root), run_id=run_id,
                                       dataset_id=dataset_id, data_format=data_format,
                                       path=path)
        file = open(path, "rb")  # closed by _blocks once sent
    except NoEpisodes as err:
        raise HTTPException(409, str(err)) from None
    except DatasetError as err:
        raise HTTPException(422, str(err)) from None
    finally:
        os.unlink(path)
    filename = written.replace("/", "_") + ".zip"
    headers = {
        "Content-Disposition": f'attachment; filename="{filename}"',
        "Content-Length": str(os.fstat(file.fileno()).st_size),
    }
    return StreamingResponse(_blocks(file), media_type="application/zip", headers=headers)

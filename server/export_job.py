"""Label exports written by a process of their own, at a lower priority than the server's.

Writing 100 000 labels takes the better part of a minute of CPU. In a thread of the server it
held the interpreter's lock against every labeller's request for all that time; in a child
process at a lower priority (`server.side_process`, which also ends it with the server) the
operating system runs the labellers' requests first and nothing is shared but the database,
which the export only reads (short read transactions that take no lock, see
`labelqueue.export`). The file goes to disk, so memory stays bounded.
"""

from __future__ import annotations

import tempfile
import zipfile
from pathlib import Path

from labelqueue import make_engine, session_factory
from rundata.label_files import ExportFormat, write_export
from server.side_process import SideProcess


def write_export_file(
    *, database_url: str, fmt: ExportFormat | str, path: str, run_id: int | None
) -> int:
    """`rundata.label_files.write_export` of the database at `database_url` into the file
    `path`; rows written. Runs in the export process: it opens its own engine."""
    engine = make_engine(database_url)
    try:
        with session_factory(engine)() as session, open(path, "wb") as out:
            return write_export(session, fmt=fmt, out=out, run_id=run_id)
    finally:
        engine.dispose()


def write_dataset_zip(*, database_url: str, clips_root: str, run_id: int,
                      dataset_id: str | None, path: str, data_format: str = "arrow") -> str:
    """Run `run_id`'s Minari dataset (`rundata.dataset.write_dataset`, in Minari's
    `data_format`) as the zip file
    `path`, its members under `<dataset id>/`, so that it unpacks into a Minari datasets
    folder; the dataset id. Runs in the export process."""
    from rundata.dataset import write_dataset

    engine = make_engine(database_url)
    try:
        with tempfile.TemporaryDirectory(prefix="sepoa-dataset-") as root, \
                session_factory(engine)() as session:
            summary = write_dataset(session, run_id=run_id, clips_root=Path(clips_root),
                                    root=Path(root), dataset_id=dataset_id,
                                    data_format=data_format)
            with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as archive:
                for file in sorted(summary.path.rglob("*")):
                    if file.is_file():
                        archive.write(file, file.relative_to(root).as_posix())
            return summary.dataset_id
    finally:
        engine.dispose()


class ExportProcess(SideProcess):
    """The export process: exports queue for it one at a time."""

    def write(
        self, *, database_url: str, fmt: ExportFormat | str, path: str, run_id: int | None
    ) -> int:
        """Write the export into `path` in the export process (blocking); rows written.
        NotFound and ValueError come back as they were raised there."""
        return self.run(write_export_file, database_url=database_url, fmt=fmt, path=path,
                        run_id=run_id)

    def write_dataset(self, *, database_url: str, clips_root: str, run_id: int,
                      dataset_id: str | None, path: str, data_format: str = "arrow") -> str:
        """`write_dataset_zip` in the export process (blocking); the dataset id."""
        return self.run(write_dataset_zip, database_url=database_url, clips_root=clips_root,
                        run_id=run_id, dataset_id=dataset_id, path=path,
                        data_format=data_format)

"""Label exports written by a process of their own, at a lower priority than the server's.

Writing 100 000 labels takes the better part of a minute of CPU. In a thread of the server it
held the interpreter's lock against every labeller's request for all that time; in a child
process at `NICENESS` the operating system runs the labellers' requests first and nothing is
shared but the database, which the export only reads (short read transactions that take no
lock, see `labelqueue.export`). The file goes to disk, so memory stays bounded.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import ProcessPoolExecutor

from labelqueue import ExportFormat, make_engine, session_factory, write_export

NICENESS = 10
"""how much lower the export process's scheduling priority is than the server's"""


def _lower_priority() -> None:
    os.nice(NICENESS)


def write_export_file(
    *, database_url: str, fmt: ExportFormat | str, path: str, run_id: int | None
) -> int:
    """`labelqueue.write_export` of the database at `database_url` into the file `path`; rows
    written. Runs in the export process: it opens its own engine."""
    engine = make_engine(database_url)
    try:
        with session_factory(engine)() as session, open(path, "wb") as out:
            return write_export(session, fmt=fmt, out=out, run_id=run_id)
    finally:
        engine.dispose()


class ExportProcess:
    """One export process, started at the first export and kept for the next (starting one
    takes about a second); exports queue for it one at a time."""

    def __init__(self) -> None:
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def write(
        self, *, database_url: str, fmt: ExportFormat | str, path: str, run_id: int | None
    ) -> int:
        """Write the export into `path` in the export process (blocking); rows written.
        NotFound and ValueError come back as they were raised there."""
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=1,
                    # Not forked: the server has threads (and a database pool) to not copy.
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_lower_priority,
                )
            pool = self._pool
        future = pool.submit(
            write_export_file, database_url=database_url, fmt=fmt, path=path, run_id=run_id
        )
        return future.result()

    def close(self) -> None:
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown(cancel_futures=True)
                self._pool = None

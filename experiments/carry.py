"""Carrying an unfinished grid to another machine: `sepoa experiment pack` writes one archive
of what the grid's runs need to go on there from where they stopped.

A run resumes from the checkpoint in its folder (`trainer.worker`), so the archive holds, under
paths relative to the results folder:
- every unfinished run's folder as it is on disk (checkpoint, metric files, labels), without
  its TensorBoard files, which a resumed run writes again;
- every finished run's results (`done.json` and the files beside it, not its checkpoint or
  TensorBoard files), so that the launcher there counts it as finished; left out with
  `unfinished_only` when the finished runs travel another way;
- the skill snapshots, finished and partial (`<results>/snapshots`): a partial one is a
  pretraining's checkpoint;
- each packed run's episode store (`<results>/clips/run-<id>/episodes/`, `rundata.episodes`,
  where the launcher's and Slurm's workers keep it), which a resumed run's later queries and
  the dataset export read; its folder is named by the run's id in the queue, so the grid's
  queue is read for the ids (and for the runs a live worker holds), whichever it is;
- the grid's spec as the launcher wrote it, its training periods so far (`sessions.csv`,
  `experiments.sessions`) and its stop rule's record (`stop_rule.json`), beside its runs;
- the queue database, when it is a SQLite file (the launcher's `<results>/queue.db`, or the file
  a SQLite URL names), copied with SQLite's backup (a consistent copy of a database in use) to
  `queue.db`, the launcher's default there: runs keep their ids, label counts and statuses. A
  PostgreSQL queue stays where it is, reachable from the other machine, the runs' ids with it.

There: `tar -xzf ARCHIVE -C <results>` and `sepoa experiment run SPEC --results <results>`
(with the PostgreSQL queue's URL, for a grid whose queue is one). Without a queue to read
(no `<results>/queue.db` and no URL given) nothing is packed: the archive would leave the
episode stores behind, and the runs resumed from it would miss their stored episodes.

A worker writes its run's checkpoint at episode ends, rounds' ends and when stopped, so packing
while a worker trains would carry a checkpoint behind its run: a run held by a worker that
heartbeat within `DEAD_WORKER_AFTER_S` is refused, with the worker named.
"""

from __future__ import annotations

import sqlite3
import tarfile
import tempfile
import uuid
from contextlib import closing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import text

from experiments.queue import HELD, grid_key
from experiments.sessions import FILE as SESSIONS
from experiments.spec import Spec
from experiments.stop_rule import FILE as STOP_RULE
from labelqueue import DEAD_WORKER_AFTER_S, make_engine
from labelqueue.schema import sqlite_file
from rundata.episodes import episodes_dir

GRID_FILES = ("spec.toml", SESSIONS, STOP_RULE)
"""the grid's own files, beside its runs"""

LEFT_BEHIND_IN_RUNS = {"tb"}
"""folders of a run that a resumed run writes again"""
LEFT_BEHIND_WHEN_FINISHED = {"tb", "checkpoint.pt"}


class PackError(ValueError):
    """The grid cannot be packed now; the message says why and what to do."""


@dataclass
class Packed:
    unfinished: int
    finished: int
    snapshots: int
    database: bool
    size: int
    episode_stores: int = 0
    """runs whose episode store was packed"""


def _grid_rows(url: str, spec: Spec, columns: str) -> list[Any]:
    """`columns` of the spec's runs in the queue at `url`. Plain SQL on columns every schema of
    the queue has, so a grid trained by an older sepoa can be packed by a newer one; a SQLite
    file is opened read-only; the key's prefix compared as text, not with LIKE, where `_` would
    match any character."""
    prefix = f"{spec.name}/"
    sql = f"SELECT {columns} FROM runs WHERE substr(grid_key, 1, :length) = :prefix"
    params = {"length": len(prefix), "prefix": prefix}
    database = sqlite_file(url)
    if database is not None:
        with closing(sqlite3.connect(f"file:{database}?mode=ro", uri=True)) as db:
            return db.execute(sql, params).fetchall()
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return [tuple(row) for row in connection.execute(text(sql), params)]
    finally:
        engine.dispose()


def held_runs(url: str, spec: Spec, now: datetime | None = None) -> list[str]:
    """Lines naming the spec's runs that a live worker holds in the queue at `url`."""
    now = now or datetime.now(UTC).replace(tzinfo=None)
    rows = _grid_rows(url, spec, "grid_key, status, worker_id, heartbeat_at")
    lines = []
    for key, status, worker, beat in rows:
        if status not in HELD or worker is None or beat is None:
            continue
        if isinstance(beat, str):  # SQLite's text, in UTC
            beat = datetime.fromisoformat(beat)
        if beat.tzinfo is not None:
            beat = beat.astimezone(UTC).replace(tzinfo=None)
        age = (now - beat).total_seconds()
        if age < DEAD_WORKER_AFTER_S:
            lines.append(f"{key} ({status}, worker {worker}, heartbeat {age:.0f} s ago)")
    return lines


def pack(spec: Spec, results: Path, out: Path, unfinished_only: bool = False,
         database_url: str | None = None) -> Packed:
    """The grid packed into `out`, its runs' ids and holders read from the queue at
    `database_url` (default `<results>/queue.db`). PackError when there is no such SQLite
    file, a live worker holds a run, or the SQLite file cannot be read."""
    url = database_url or f"sqlite:///{(results / 'queue.db').absolute()}"
    database = sqlite_file(url)
    if database is not None and not Path(database).is_file():
        raise PackError(
            f"no queue database at {database}: the runs' episode stores are named by their "
            "ids in the grid's queue, so pack reads it; for a grid whose queue is PostgreSQL "
            "(or a SQLite file elsewhere) give its --database-url or --database-url-file (or "
            "SEPOA_DATABASE_URL), as to `experiment run`")
    try:
        return _pack(spec, results, url, out, unfinished_only)
    except sqlite3.Error as err:
        raise PackError(f"the queue database {database}: {err}") from None


def _pack(spec: Spec, results: Path, url: str, out: Path, unfinished_only: bool) -> Packed:
    if held := held_runs(url, spec):
        raise PackError(
            f"{len(held)} run(s) are held by live workers: {'; '.join(held)}. Stop their "
            "launcher or workers first (Ctrl-C or SIGTERM: each checkpoints its run and "
            "releases it), so the archive holds each run's latest checkpoint")
    out.parent.mkdir(parents=True, exist_ok=True)
    # A name of its own beside `out`: two packs to one path never write into one file. Made
    # by tarfile with the umask's mode, as `out` itself would be (mkstemp's is 0600).
    partial = out.with_name(f".{out.name}.{uuid.uuid4().hex[:12]}.partial")
    try:
        counts = _write(partial, spec, results, url, unfinished_only)
        partial.replace(out)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return Packed(counts["unfinished"], counts["finished"], counts["snapshots"],
                  sqlite_file(url) is not None, out.stat().st_size, counts["episode_stores"])


def copy_sqlite(database: Path | str, copy: Path) -> None:
    """`database` copied to `copy` with SQLite's backup: a consistent copy of a file that
    workers may be writing to."""
    with closing(sqlite3.connect(database)) as source, closing(sqlite3.connect(copy)) as target:
        source.backup(target)


def _write(tar_path: Path, spec: Spec, results: Path, url: str,
           unfinished_only: bool) -> dict[str, int]:
    """The archive at `tar_path`; how many unfinished and finished runs, episode stores and
    snapshot files it holds."""
    counts = {"unfinished": 0, "finished": 0, "snapshots": 0, "episode_stores": 0}
    ids = dict(_grid_rows(url, spec, "grid_key, id"))
    with tarfile.open(tar_path, "w:gz") as tar:
        # What `sepoa report` reads, the grid's training time so far (experiments.sessions)
        # and the seeds its stop rule left out.
        for name in GRID_FILES:
            if (results / spec.name / name).exists():
                tar.add(results / spec.name / name, f"{spec.name}/{name}")
        for run in spec.runs():
            key = grid_key(spec, run)
            folder = results / key
            if not folder.is_dir():
                continue
            finished = (folder / "done.json").exists()
            if finished and unfinished_only:
                continue
            left_behind = LEFT_BEHIND_WHEN_FINISHED if finished else LEFT_BEHIND_IN_RUNS
            _add_folder(tar, folder, key, left_behind)
            counts["finished" if finished else "unfinished"] += 1
            episodes = episodes_dir(results / "clips", ids[key]) if key in ids else None
            if episodes is not None and episodes.is_dir():
                _add_folder(tar, episodes, episodes.relative_to(results).as_posix(), set())
                counts["episode_stores"] += 1
        snapshots = results / "snapshots"
        for path in sorted(snapshots.glob("*")) if snapshots.is_dir() else []:
            if path.is_file() and path.suffix != ".lock":
                tar.add(path, f"snapshots/{path.name}")
                counts["snapshots"] += 1
        if (database := sqlite_file(url)) is not None:
            with tempfile.TemporaryDirectory() as tmp:
                copy = Path(tmp) / "queue.db"
                copy_sqlite(database, copy)
                tar.add(copy, "queue.db")
    return counts


def _add_folder(tar: tarfile.TarFile, folder: Path, name: str, left_behind: set[str]) -> None:
    for path in sorted(folder.iterdir()):
        if path.name in left_behind or path.name.endswith(".tmp"):  # half written by a
            continue  # writer that was killed: its file is the one without .tmp
        if path.is_dir():
            _add_folder(tar, path, f"{name}/{path.name}", set())
        else:
            tar.add(path, f"{name}/{path.name}")

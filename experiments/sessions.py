"""When a grid's local workers ran: each `sepoa experiment run` that trains appends its period to
`<results>/<spec name>/sessions.csv` (started, ended, workers, threads, how it ended), so that a
stop rule in wall time ("no seed starts after 10 h") can be read off `sepoa experiment status`
across sessions and restarts, with the time between them, when nothing ran, left out.

While it runs, a launcher writes the time into its row's `alive_at` every `BEAT_S`. One killed
outright (SIGKILL, the machine lost) leaves its row without an end, and it counts up to its last
`alive_at`; a row without an end counts up to now while its `alive_at` is recent (the launcher
runs). A row without an end or an `alive_at` (written before the column existed) counts up to
now while it is the newest, and not at all once a later session has begun, which `worked` says.
Time two sessions share (two launchers on one grid at once) counts once: the sum is wall time.

Two launchers on one spec share the file: each change is a read-modify-write under an exclusive
lock on `sessions.csv.lock`, written to a temporary file of its own and renamed, and a launcher
finds its row by its `id` (rows written before the column existed have none).
"""

from __future__ import annotations

import csv
import fcntl
import os
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

FILE = "sessions.csv"
FIELDS = ("started_at", "ended_at", "workers", "threads", "ended_by", "alive_at", "id")
BEAT_S = 60.0
"""how often a running launcher writes `alive_at`"""
RUNNING_WITHIN_S = 3 * BEAT_S
"""an unended newest row whose `alive_at` is older than this was killed: it runs no more"""


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _write(path: Path, rows: list[dict[str, str]]) -> None:
    # A name of its own, made with the umask's mode as the file itself would be.
    name = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        with name.open("x", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=FIELDS, restval="", extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
        os.replace(name, path)
    except BaseException:
        name.unlink(missing_ok=True)
        raise


def _change(path: Path, edit: Callable[[list[dict[str, str]]], None]) -> None:
    """Read the rows, `edit` them in place and write them back, under the file's lock: another
    launcher's change between the read and the write would be lost."""
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released as the file closes
        rows = _rows(path)
        edit(rows)
        _write(path, rows)


class Session:
    """One launcher's period: `end` records how it ended (else "error", for an exception)."""

    def __init__(self) -> None:
        self.ended_by = "error"

    def end(self, ended_by: str) -> None:
        self.ended_by = ended_by


def _stamp() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


def _to_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


@contextmanager
def recorded_session(folder: Path, *, workers: int, threads: int,
                     now: datetime | None = None, beat_s: float = BEAT_S,
                     echo: Callable[[str], None] = _to_stderr) -> Iterator[Session]:
    """Record a training period of the grid whose results are in `folder`: its row is written
    as it starts, its `alive_at` every `beat_s` while it runs, and its end as it ends, however
    it ends. `echo` says when a beat could not be written."""
    path = folder / FILE
    started = (now or datetime.now(UTC)).isoformat(timespec="seconds")
    mine = uuid.uuid4().hex[:12]  # two launchers may start within one second
    _change(path, lambda rows: rows.append({
        "started_at": started, "ended_at": "", "workers": str(workers), "threads": str(threads),
        "ended_by": "", "alive_at": started, "id": mine}))
    done = threading.Event()

    def update(**fields: str) -> None:
        def edit(rows: list[dict[str, str]]) -> None:
            for row in rows:
                if row.get("id") == mine and not row["ended_at"]:
                    row.update(fields)
        _change(path, edit)

    def beat() -> None:
        while not done.wait(beat_s):
            try:
                update(alive_at=_stamp())
            except Exception as error:  # a full disk, a hand-edited file: the beat goes on,
                # or the session would soon read as killed while its workers train
                echo(f"{path}: the launcher's sign of life could not be written "
                     f"({type(error).__name__}: {error}); trying again in {beat_s:g} s")

    beating = threading.Thread(target=beat, name="session-beat", daemon=True)
    beating.start()
    session = Session()
    try:
        yield session
    finally:
        done.set()
        beating.join()
        stamp = _stamp()
        update(ended_at=stamp, alive_at=stamp, ended_by=session.ended_by)


@dataclass(frozen=True)
class Worked:
    seconds: float
    """wall time the grid's local workers ran, over its sessions (time they share once)"""
    sessions: int
    running_since: datetime | None
    """the start of the newest session that runs (no end, a recent sign of life)"""
    unended: int
    """sessions without an end and not running (killed outright): counted up to their last
    `alive_at`, or not at all without one"""

    def text(self, duration: str) -> str:
        """One line for `sepoa experiment status`, `duration` the seconds written out."""
        line = (f"worked (local workers' wall time, {FILE}): {duration} over {self.sessions} "
                f"session(s)")
        if self.running_since is not None:
            line += f", the last running since {self.running_since:%Y-%m-%d %H:%M} UTC"
        if self.unended:
            line += (f"; {self.unended} session(s) ended without a record (killed outright): "
                     "counted up to their last sign of life, where they left one")
        return line


def worked(folder: Path, now: datetime | None = None) -> Worked | None:
    """The grid's training time so far; None before its first recorded session. Sessions
    that overlap (two launchers on one grid) count their common time once: it is wall time."""
    rows = _rows(folder / FILE)
    if not rows:
        return None
    now = now or datetime.now(UTC)
    periods: list[tuple[datetime, datetime]] = []
    unended, running = 0, None
    for i, row in enumerate(rows):
        start = datetime.fromisoformat(row["started_at"])
        alive = datetime.fromisoformat(row["alive_at"]) if row.get("alive_at") else None
        if row["ended_at"]:
            periods.append((start, datetime.fromisoformat(row["ended_at"])))
        # A recent sign of life: it runs, newest or not (another launcher may have started
        # since); without the column, only the newest row can be running.
        elif (alive is not None and (now - alive).total_seconds() <= RUNNING_WITHIN_S) \
                or (alive is None and i == len(rows) - 1):
            periods.append((start, now))
            running = start if running is None else max(running, start)
        else:
            unended += 1
            if alive is not None:
                periods.append((start, alive))
    return Worked(_union_seconds(periods), len(rows), running, unended)


def _union_seconds(periods: list[tuple[datetime, datetime]]) -> float:
    """The seconds covered by at least one of `periods` (start, end)."""
    seconds, reached = 0.0, None
    for start, end in sorted(periods):
        if reached is not None:
            start = max(start, reached)
        if end > start:
            seconds += (end - start).total_seconds()
        reached = end if reached is None else max(reached, end)
    return seconds

"""When a grid's local workers ran: each `sepoa experiment run` that trains appends its period to
`<results>/<spec name>/sessions.csv` (started, ended, workers, threads, how it ended), so that a
stop rule in wall time ("no seed starts after 10 h") can be read off `sepoa experiment status`
across sessions and restarts, with the time between them, when nothing ran, left out.

A launcher killed outright (SIGKILL, the machine lost) leaves its row without an end: it counts
up to now while it is the newest row (the launcher may still run), and not at all once a later
session has begun, which `worked` says.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

FILE = "sessions.csv"
FIELDS = ("started_at", "ended_at", "workers", "threads", "ended_by")


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _write(path: Path, rows: list[dict[str, str]]) -> None:
    tmp = path.with_suffix(".tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    tmp.replace(path)


class Session:
    """One launcher's period: `end` records how it ended (else "error", for an exception)."""

    def __init__(self) -> None:
        self.ended_by = "error"

    def end(self, ended_by: str) -> None:
        self.ended_by = ended_by


@contextmanager
def recorded_session(folder: Path, *, workers: int, threads: int,
                     now: datetime | None = None) -> Iterator[Session]:
    """Record a training period of the grid whose results are in `folder`: its row is written
    as it starts and given its end as it ends, however it ends."""
    path = folder / FILE
    started = (now or datetime.now(UTC)).isoformat(timespec="seconds")
    _write(path, [*_rows(path), {"started_at": started, "ended_at": "", "workers": str(workers),
                                 "threads": str(threads), "ended_by": ""}])
    session = Session()
    try:
        yield session
    finally:
        rows = _rows(path)
        for row in rows:
            if row["started_at"] == started and not row["ended_at"]:
                row["ended_at"] = datetime.now(UTC).isoformat(timespec="seconds")
                row["ended_by"] = session.ended_by
        _write(path, rows)


@dataclass(frozen=True)
class Worked:
    seconds: float
    """wall time the grid's local workers ran, summed over its sessions"""
    sessions: int
    running_since: datetime | None
    """the newest session's start, while it has no end (it runs, or was killed outright)"""
    unended: int
    """older sessions without an end (killed outright): not counted"""

    def text(self, duration: str) -> str:
        """One line for `sepoa experiment status`, `duration` the seconds written out."""
        line = (f"worked (local workers' wall time, {FILE}): {duration} over {self.sessions} "
                f"session(s)")
        if self.running_since is not None:
            line += f", the last running since {self.running_since:%Y-%m-%d %H:%M} UTC"
        if self.unended:
            line += (f"; {self.unended} earlier session(s) ended without a record (killed "
                     "outright): not counted")
        return line


def worked(folder: Path, now: datetime | None = None) -> Worked | None:
    """The grid's training time so far; None before its first recorded session."""
    rows = _rows(folder / FILE)
    if not rows:
        return None
    now = now or datetime.now(UTC)
    seconds, unended, running = 0.0, 0, None
    for i, row in enumerate(rows):
        start = datetime.fromisoformat(row["started_at"])
        if row["ended_at"]:
            seconds += (datetime.fromisoformat(row["ended_at"]) - start).total_seconds()
        elif i == len(rows) - 1:
            seconds += max((now - start).total_seconds(), 0.0)
            running = start
        else:
            unended += 1
    return Worked(seconds, len(rows), running, unended)

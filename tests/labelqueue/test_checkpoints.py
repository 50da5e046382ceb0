"""The server's SQLite engine leaves the WAL's checkpoints to a thread of its own, so no commit
blocks the event loop copying the WAL back into the database file."""

from __future__ import annotations

import sqlite3
import threading
import time
from pathlib import Path

from sqlalchemy import text

from labelqueue import make_engine, migrate


def wal_frames(path: Path) -> tuple[int, int]:
    """(frames in the WAL, frames of it already copied into the database file)."""
    with sqlite3.connect(path) as connection:
        _, log, copied = connection.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
    return log, copied


def checkpointers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "sqlite-checkpoint"]


def write_pages(engine, rows: int) -> None:
    with engine.begin() as connection:
        connection.execute(text("CREATE TABLE IF NOT EXISTS filler (x BLOB)"))
        for _ in range(rows):
            connection.execute(text("INSERT INTO filler VALUES (randomblob(4000))"))


def test_commits_leave_the_wal_to_the_checkpoint_thread(tmp_path: Path) -> None:
    path = tmp_path / "queue.db"
    migrate(f"sqlite:///{path}")
    before = len(checkpointers())
    engine = make_engine(f"sqlite:///{path}", background_checkpoints=True)
    try:
        assert len(checkpointers()) == before + 1
        with engine.connect() as connection:
            assert connection.exec_driver_sql("PRAGMA wal_autocheckpoint").scalar() == 0
        write_pages(engine, 1500)  # past SQLite's 1 000-page threshold for a commit's own
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # the thread copies the WAL back
            log, copied = wal_frames(path)
            if log >= 1500 and copied == log:
                break
            time.sleep(0.1)
        assert log >= 1500 and copied == log
    finally:
        engine.dispose()
    assert len(checkpointers()) == before  # it stops with the engine


def test_other_engines_keep_sqlites_own_checkpoints(tmp_path: Path) -> None:
    path = tmp_path / "queue.db"
    migrate(f"sqlite:///{path}")
    before = len(checkpointers())
    engine = make_engine(f"sqlite:///{path}")
    try:
        assert len(checkpointers()) == before
        with engine.connect() as connection:
            assert connection.exec_driver_sql("PRAGMA wal_autocheckpoint").scalar() == 1000
    finally:
        engine.dispose()

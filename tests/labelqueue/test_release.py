"""A worker told to go releases its run at once (release_run): queued again for any worker, a
paused run kept paused, a stopping one stopped; the runs held by workers gone silent
(silent_holders); and database URLs that never show their password (mask_url, URL files)."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import (
    Conflict,
    InvalidTransition,
    Run,
    RunStatus,
    claim_run,
    create_run,
    database_url,
    heartbeat,
    heartbeat_age,
    mask_url,
    read_run,
    read_url_file,
    release_run,
    set_run_status,
    silent_holders,
    stop_run,
    url_has_secret,
)
from labelqueue.models import utcnow


def claimed(session: Session, worker: str, name: str = "r") -> Run:
    create_run(session, name=name, task="dmc:walker_run", algo="pebble", budget=50)
    run = claim_run(session, worker_id=worker)
    assert run is not None and run.worker_id == worker
    return run


def test_a_released_run_is_queued_again_at_once_with_its_step(session: Session) -> None:
    run = claimed(session, "w1")
    heartbeat(session, run_id=run.id, worker_id="w1", step=600, progress={"episode": 3})
    released = release_run(session, run_id=run.id, worker_id="w1")
    assert (released.status, released.worker_id, released.heartbeat_at) == (
        RunStatus.QUEUED, None, None)
    assert (released.step, released.progress, released.finished_at) == (600, {"episode": 3},
                                                                        None)
    # Taken by the next worker that looks, not after DEAD_WORKER_AFTER_S.
    again = claim_run(session, worker_id="w2")
    assert again is not None and (again.id, again.status) == (run.id, RunStatus.RUNNING)
    # The first worker's word no longer counts.
    with pytest.raises(Conflict):
        heartbeat(session, run_id=run.id, worker_id="w1", step=800)
    with pytest.raises(Conflict):
        release_run(session, run_id=run.id, worker_id="w1")


def test_a_paused_run_stays_paused_and_a_stopping_one_stops(session: Session) -> None:
    paused = claimed(session, "w1", "paused")
    set_run_status(session, run_id=paused.id, status=RunStatus.PAUSED)
    kept = release_run(session, run_id=paused.id, worker_id="w1")
    assert (kept.status, kept.worker_id) == (RunStatus.PAUSED, None)
    assert claim_run(session, worker_id="w2") is None  # the operator paused it
    set_run_status(session, run_id=paused.id, status=RunStatus.RUNNING)  # resume: for anyone
    resumed = claim_run(session, worker_id="w2")
    assert resumed is not None and (resumed.id, resumed.worker_id) == (paused.id, "w2")

    stopping = claimed(session, "w3", "stopping")
    set_run_status(session, run_id=stopping.id, status=RunStatus.STOPPING)
    stopped = release_run(session, run_id=stopping.id, worker_id="w3")
    assert stopped.status is RunStatus.STOPPED and stopped.finished_at is not None
    assert read_run(session, run_id=stopping.id).finished_at == stopped.finished_at


def test_a_stop_ends_at_once_a_run_no_worker_holds(session: Session) -> None:
    held = claimed(session, "w1", "held")
    assert stop_run(session, run_id=held.id).status is RunStatus.STOPPING
    paused = claimed(session, "w2", "paused")
    set_run_status(session, run_id=paused.id, status=RunStatus.PAUSED)
    release_run(session, run_id=paused.id, worker_id="w2")
    stopped = stop_run(session, run_id=paused.id)
    assert (stopped.status, stopped.worker_id) == (RunStatus.STOPPED, None)
    assert stopped.finished_at is not None
    create_run(session, name="queued", task="dmc:walker_run", algo="pebble", budget=50)
    queued = claim_run(session, worker_id="w3", skip=[held.id])
    assert queued is not None
    release_run(session, run_id=queued.id, worker_id="w3", untouched=True)
    assert stop_run(session, run_id=queued.id).status is RunStatus.STOPPED
    with pytest.raises(InvalidTransition, match="is stopping; it cannot be stopped"):
        stop_run(session, run_id=held.id)
    assert stop_run(session, run_id=held.id, force=True).status is RunStatus.STOPPED


def test_runs_held_by_silent_workers_with_their_heartbeat_age(session: Session) -> None:
    fresh, quiet = claimed(session, "alive", "fresh"), claimed(session, "quiet", "quiet")
    for run, age in ((fresh, 5), (quiet, 90)):
        session.execute(update(Run).where(Run.id == run.id).values(
            heartbeat_at=utcnow() - timedelta(seconds=age)))
    session.commit()
    held = silent_holders(session, worker_id="other")
    assert [(r.id, r.worker_id) for r in held] == [(quiet.id, "quiet")]
    assert 89 < (heartbeat_age(held[0]) or 0) < 120
    assert silent_holders(session, worker_id="quiet") == []  # its own run is not news to it
    assert heartbeat_age(release_run(session, run_id=fresh.id, worker_id="alive")) is None


def test_a_database_url_never_shows_its_password(tmp_path: Path) -> None:
    assert mask_url("postgresql+psycopg://sepoa:hunter2@db:5432/q") == \
        "postgresql+psycopg://sepoa:***@db:5432/q"
    assert mask_url("postgresql+psycopg://sepoa@/q?host=/run/pg&password=hunter2") == \
        "postgresql+psycopg://sepoa@/q?host=%2Frun%2Fpg&password=***"
    assert mask_url("sqlite:////data/queue.db") == "sqlite:////data/queue.db"
    assert [url_has_secret(u) for u in ("postgresql://u:p@h/d", "postgresql://u@h/d?password=p",
                                        "postgresql://u@h/d", "sqlite:///q.db")] == \
        [True, True, False, False]

    path = tmp_path / "url"
    path.write_text("\n# the queue\npostgresql+psycopg://u:p@h/d\n")
    path.chmod(0o600)
    assert read_url_file(path) == "postgresql+psycopg://u:p@h/d"
    # Flags first, then the environment's URL, then its file.
    env = {"SEPOA_DATABASE_URL_FILE": str(path)}
    assert database_url(None, None, env) == "postgresql+psycopg://u:p@h/d"
    assert database_url(None, None, env | {"SEPOA_DATABASE_URL": "sqlite:///a"}) == "sqlite:///a"
    assert database_url("sqlite:///b", None, env | {"SEPOA_DATABASE_URL": "sqlite:///a"}) == \
        "sqlite:///b"
    assert database_url(None, None, {}) is None
    with pytest.raises(ValueError, match="not both"):
        database_url("sqlite:///b", str(path), {})
    path.chmod(0o640)
    with pytest.raises(ValueError, match=r"may be read by other users \(mode 640\); chmod 600"):
        read_url_file(path)
    with pytest.raises(ValueError, match="missing: No such file or directory"):
        read_url_file(tmp_path / "missing")

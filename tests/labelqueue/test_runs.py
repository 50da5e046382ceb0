"""Workers claim runs, heartbeat, and obey the operator's pause, resume and stop."""

from __future__ import annotations

from datetime import timedelta

import pytest
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from labelqueue import (
    Conflict,
    InvalidTransition,
    NotFound,
    Run,
    RunStatus,
    TeacherKind,
    Worker,
    claim_run,
    create_run,
    finish_run,
    heartbeat,
    other_claimable,
    set_run_status,
    set_teacher,
)
from labelqueue.models import utcnow


def new_run(session: Session, name: str = "r") -> Run:
    return create_run(session, name=name, task="dmc:walker_run", algo="pebble", budget=50)


def age_heartbeat(session: Session, run_id: int, seconds: float) -> None:
    """Pretend the run's worker last heartbeated `seconds` ago."""
    session.execute(
        update(Run)
        .where(Run.id == run_id)
        .values(heartbeat_at=utcnow() - timedelta(seconds=seconds))
    )
    session.commit()


def test_workers_claim_queued_runs_oldest_first(session: Session) -> None:
    first, second = new_run(session, "first"), new_run(session, "second")
    assert first.status is RunStatus.QUEUED

    got = claim_run(session, worker_id="w1")
    assert got is not None and got.id == first.id
    assert got.status is RunStatus.RUNNING and got.worker_id == "w1"
    assert got.started_at is not None and got.heartbeat_at is not None
    got = claim_run(session, worker_id="w2")
    assert got is not None and got.id == second.id
    assert claim_run(session, worker_id="w3") is None

    workers = {w.id: w.run_id for w in session.scalars(select(Worker))}
    assert workers == {"w1": first.id, "w2": second.id, "w3": None}


def test_a_worker_skips_the_runs_it_set_aside_while_others_are_claimable(
        session: Session) -> None:
    first, second = new_run(session, "first"), new_run(session, "second")
    assert other_claimable(session, worker_id="w1", besides={first.id})
    assert not other_claimable(session, worker_id="w1", besides={first.id, second.id})

    got = claim_run(session, worker_id="w1", skip={first.id})
    assert got is not None and got.id == second.id
    assert claim_run(session, worker_id="w2", skip={first.id}) is None
    assert not other_claimable(session, worker_id="w2", besides={first.id})
    got = claim_run(session, worker_id="w2")
    assert got is not None and got.id == first.id


def test_a_dead_workers_run_is_claimed_after_the_heartbeat_timeout(session: Session) -> None:
    run = new_run(session)
    claim_run(session, worker_id="dead")
    started = session.get(Run, run.id).started_at  # type: ignore[union-attr]
    session.commit()

    age_heartbeat(session, run.id, 30)
    assert claim_run(session, worker_id="alive", stale_after=60) is None  # still within timeout

    age_heartbeat(session, run.id, 90)
    taken = claim_run(session, worker_id="alive", stale_after=60)
    assert taken is not None and taken.id == run.id and taken.worker_id == "alive"
    assert taken.started_at == started  # a takeover, not a fresh start

    # The old worker wakes up: it no longer owns the run and must stop writing to it.
    with pytest.raises(Conflict, match="alive"):
        heartbeat(session, run_id=run.id, worker_id="dead", step=5)
    with pytest.raises(Conflict):
        finish_run(session, run_id=run.id, worker_id="dead")


def test_a_restarted_worker_takes_back_its_own_runs_first(session: Session) -> None:
    older = new_run(session, "older")
    mine = new_run(session, "mine")
    set_run_status(session, run_id=older.id, status=RunStatus.STOPPED)
    claim_run(session, worker_id="w1")  # takes "mine"
    set_run_status(session, run_id=mine.id, status=RunStatus.PAUSED)
    queued = new_run(session, "queued")

    # Killed and restarted under the same id: no heartbeat timeout to wait for, and the run
    # stays paused; another worker id gets the queued run, not this one.
    back = claim_run(session, worker_id="w1")
    assert back is not None and back.id == mine.id and back.status is RunStatus.PAUSED
    other = claim_run(session, worker_id="w2")
    assert other is not None and other.id == queued.id


def test_heartbeat_records_progress_and_tells_the_worker_the_status(session: Session) -> None:
    run = new_run(session)
    claim_run(session, worker_id="w")
    status = heartbeat(session, run_id=run.id, worker_id="w", step=1234, progress={"ret": 5.0})
    assert status is RunStatus.RUNNING
    stored = session.get(Run, run.id, populate_existing=True)
    assert stored is not None and stored.step == 1234 and stored.progress == {"ret": 5.0}
    session.commit()
    with pytest.raises(NotFound):
        heartbeat(session, run_id=999, worker_id="w", step=0)


def test_pause_resume_stop_as_the_worker_sees_them(session: Session) -> None:
    run = new_run(session)
    claim_run(session, worker_id="w")

    assert set_run_status(session, run_id=run.id, status="paused").status is RunStatus.PAUSED
    assert heartbeat(session, run_id=run.id, worker_id="w", step=1) is RunStatus.PAUSED
    # A paused run whose heartbeat is old is not claimed: the worker idles, it is not dead.
    age_heartbeat(session, run.id, 10_000)
    assert claim_run(session, worker_id="other") is None

    assert set_run_status(session, run_id=run.id, status="running").status is RunStatus.RUNNING
    assert heartbeat(session, run_id=run.id, worker_id="w", step=2) is RunStatus.RUNNING

    set_run_status(session, run_id=run.id, status=RunStatus.STOPPING)
    assert heartbeat(session, run_id=run.id, worker_id="w", step=3) is RunStatus.STOPPING
    done = finish_run(session, run_id=run.id, worker_id="w", status="stopped")
    assert done.status is RunStatus.STOPPED and done.finished_at is not None


@pytest.mark.parametrize(
    ("start", "target"),
    [
        (RunStatus.QUEUED, RunStatus.PAUSED),
        (RunStatus.QUEUED, RunStatus.RUNNING),
        (RunStatus.RUNNING, RunStatus.FINISHED),
        (RunStatus.RUNNING, RunStatus.QUEUED),
        (RunStatus.PAUSED, RunStatus.PAUSED),
        (RunStatus.FINISHED, RunStatus.RUNNING),
        (RunStatus.FINISHED, RunStatus.QUEUED),
        (RunStatus.STOPPED, RunStatus.RUNNING),
    ],
)
def test_invalid_operator_moves_raise_and_change_nothing(
    session: Session, start: RunStatus, target: RunStatus
) -> None:
    run = new_run(session)
    if start is not RunStatus.QUEUED:
        claim_run(session, worker_id="w")
    if start is RunStatus.PAUSED:
        set_run_status(session, run_id=run.id, status="paused")
    if start is RunStatus.FINISHED:
        finish_run(session, run_id=run.id, worker_id="w")
    if start is RunStatus.STOPPED:
        set_run_status(session, run_id=run.id, status="stopping")
        finish_run(session, run_id=run.id, worker_id="w", status="stopped")

    with pytest.raises(InvalidTransition, match=f"is {start}; it cannot be made {target}"):
        set_run_status(session, run_id=run.id, status=target)
    assert session.get(Run, run.id, populate_existing=True).status is start  # type: ignore[union-attr]


def test_cancel_a_queued_run_and_requeue_a_failed_one(session: Session) -> None:
    cancelled = new_run(session, "cancelled")
    assert (
        set_run_status(session, run_id=cancelled.id, status="stopped").status is RunStatus.STOPPED
    )
    assert claim_run(session, worker_id="w") is None

    failing = new_run(session, "failing")
    claim_run(session, worker_id="w")
    failed = finish_run(session, run_id=failing.id, worker_id="w", status="failed", error="boom")
    assert failed.status is RunStatus.FAILED and failed.error == "boom"

    requeued = set_run_status(session, run_id=failing.id, status="queued")
    assert requeued.worker_id is None and requeued.error is None and requeued.finished_at is None
    again = claim_run(session, worker_id="w2")
    assert again is not None and again.id == failing.id
    with pytest.raises(Conflict):
        heartbeat(session, run_id=failing.id, worker_id="w", step=0)


def test_a_stop_whose_worker_died_can_be_forced(session: Session) -> None:
    run = new_run(session)
    claim_run(session, worker_id="w")
    set_run_status(session, run_id=run.id, status="stopping")
    assert set_run_status(session, run_id=run.id, status="stopped").status is RunStatus.STOPPED
    # The worker, if it was only slow, learns the news on its next heartbeat.
    assert heartbeat(session, run_id=run.id, worker_id="w", step=9) is RunStatus.STOPPED


def test_worker_endings(session: Session) -> None:
    run = new_run(session)
    claim_run(session, worker_id="w")
    with pytest.raises(InvalidTransition):
        finish_run(session, run_id=run.id, worker_id="w", status="paused")
    with pytest.raises(Conflict):
        finish_run(session, run_id=run.id, worker_id="someone-else")
    assert finish_run(session, run_id=run.id, worker_id="w").status is RunStatus.FINISHED
    with pytest.raises(InvalidTransition):
        finish_run(session, run_id=run.id, worker_id="w", status="failed")


def test_set_teacher(session: Session) -> None:
    run = new_run(session)
    assert run.teacher is TeacherKind.HUMAN and run.teacher_params == {}
    changed = set_teacher(session, run_id=run.id, teacher="scripted", params={"eps": 0.3})
    assert changed.teacher is TeacherKind.SCRIPTED and changed.teacher_params == {"eps": 0.3}
    with pytest.raises(NotFound):
        set_teacher(session, run_id=run.id + 1, teacher="human")


def test_the_budget_is_spent_when_it_cannot_pay_one_more_query(session: Session) -> None:
    from labelqueue.runs import budget_spent

    run = create_run(session, name="k3", task="dmc:walker_run", algo="pebble", budget=40,
                     config={"feedback.labels_per_query": 3})
    for used, spent in ((36, False), (37, False), (38, True), (39, True), (40, True)):
        run.labels_used = used  # a detached row: what the trainer's counts would make it
        assert budget_spent(run) is spent, used
    plain = new_run(session, "k1")
    plain.labels_used = 49
    assert not budget_spent(plain)
    plain.labels_used = 50
    assert budget_spent(plain)

"""Stopping a run: a run no worker holds (released while paused, or released and resumed but not
claimed again) is stopped at once, since no worker would ever claim it to end it; a run a worker
holds is stopping; a worker's claim between the operator's click and the move is no 409."""

from __future__ import annotations

from datetime import datetime

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, new_run
from sqlalchemy.orm import Session

import labelqueue.runs
from labelqueue import claim_run, make_engine, release_run, session_factory
from server.settings import Settings


def _released_while_paused(client: TestClient, session: Session) -> int:
    run_id = new_run(client)["id"]
    assert claim_run(session, worker_id="w1") is not None
    assert client.post(f"/api/runs/{run_id}/pause", headers=OPERATOR).status_code == 200
    release_run(session, run_id=run_id, worker_id="w1")  # SIGTERM while paused
    return run_id


def test_a_paused_run_its_worker_released_is_stopped_at_once(
    client: TestClient, session: Session
) -> None:
    run_id = _released_while_paused(client, session)
    stopped = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR)
    assert stopped.status_code == 200, stopped.text
    assert stopped.json()["status"] == "stopped" and stopped.json()["finished_at"] is not None
    assert claim_run(session, worker_id="w2") is None  # nothing left for a worker to end


def test_a_released_run_resumed_but_not_claimed_again_is_stopped_at_once(
    client: TestClient, session: Session
) -> None:
    run_id = _released_while_paused(client, session)
    resumed = client.post(f"/api/runs/{run_id}/resume", headers=OPERATOR).json()
    assert (resumed["status"], resumed["worker_id"]) == ("running", None)
    stopped = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).json()
    assert stopped["status"] == "stopped" and stopped["finished_at"] is not None


def test_a_run_a_worker_holds_is_stopping_until_the_worker_ends_it(
    client: TestClient, session: Session
) -> None:
    run_id = new_run(client)["id"]
    assert claim_run(session, worker_id="w1") is not None
    stopping = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).json()
    assert (stopping["status"], stopping["finished_at"]) == ("stopping", None)
    again = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR)
    assert again.status_code == 409
    assert again.json()["detail"] == f"run {run_id} is stopping; it cannot be stopped"
    forced = client.post(f"/api/runs/{run_id}/stop?force=true", headers=OPERATOR).json()
    assert forced["status"] == "stopped"


def test_a_claim_landing_as_the_stop_begins_is_no_409(
    client: TestClient, settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    run_id = new_run(client)["id"]
    engine = make_engine(settings.database_url)
    clock = labelqueue.runs.utcnow
    claimed: list[bool] = []

    def a_worker_claims_first() -> datetime:  # the stop's first look at the clock
        if not claimed:
            claimed.append(True)
            with session_factory(engine)() as other:
                assert claim_run(other, worker_id="w1") is not None
        return clock()

    monkeypatch.setattr(labelqueue.runs, "utcnow", a_worker_claims_first)
    stopped = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR)
    engine.dispose()
    assert claimed and stopped.status_code == 200, stopped.text
    assert (stopped.json()["status"], stopped.json()["worker_id"]) == ("stopping", "w1")

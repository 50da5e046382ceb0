"""The lists the runs page polls stay bounded as the database grows: the workers panel lists
the workers heard from lately (every restart of a worker adds a row that is never deleted), and
the runs come in pages."""

from __future__ import annotations

from datetime import timedelta

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, new_run
from sqlalchemy.orm import Session

from labelqueue import Worker, claim_run
from labelqueue.models import utcnow


def stale_workers(session: Session, n: int, days: float = 2.0) -> None:
    """`n` workers last heard from `days` ago: restarted processes, each a row of its own."""
    long_ago = utcnow() - timedelta(days=days)
    with session.begin():
        session.add_all(Worker(id=f"host-{pid}", host="host", first_seen_at=long_ago,
                               last_seen_at=long_ago - timedelta(seconds=pid))
                        for pid in range(n))


def test_the_workers_list_leaves_out_long_gone_workers_unless_asked(
        client: TestClient, session: Session) -> None:
    new_run(client)
    assert claim_run(session, worker_id="alive") is not None
    stale_workers(session, 300)
    with session.begin():
        session.add(Worker(id="dead-an-hour", host="host", first_seen_at=utcnow(),
                           last_seen_at=utcnow() - timedelta(hours=1)))

    listed = client.get("/api/workers", headers=OPERATOR)
    assert listed.status_code == 200, listed.text
    assert [(w["id"], w["state"]) for w in listed.json()] == [("alive", "training"),
                                                              ("dead-an-hour", "dead")]
    every = client.get("/api/workers?all=true", headers=OPERATOR).json()
    assert len(every) == 100  # the default limit, the most recently seen first
    assert [w["id"] for w in every[:4]] == ["alive", "dead-an-hour", "host-0", "host-1"]
    every = client.get("/api/workers?all=true&limit=1000", headers=OPERATOR).json()
    assert len(every) == 302
    assert len(client.get("/api/workers?all=true&limit=3", headers=OPERATOR).json()) == 3
    for bad in ("limit=0", "limit=1001", "all=maybe"):
        refused = client.get(f"/api/workers?{bad}", headers=OPERATOR)
        assert refused.status_code == 422 and refused.json()["detail"][0]["loc"][0] == "query"
    # A run's activity counts the live workers only, whatever the dead ones' number.
    queued = new_run(client, name="waits")["id"]
    activity = client.get(f"/api/runs/{queued}/activity", headers=OPERATOR).json()
    assert (activity["workers_alive"], activity["workers_idle"]) == (1, 0)


def test_runs_come_in_pages_newest_first_each_oldest_first(client: TestClient) -> None:
    ids = [new_run(client, name=f"run-{i}")["id"] for i in range(7)]
    every = client.get("/api/runs", headers=OPERATOR).json()
    assert [run["id"] for run in every] == ids  # no limit: every run, oldest first

    def page(query: str) -> list[int]:
        response = client.get(f"/api/runs?{query}", headers=OPERATOR)
        assert response.status_code == 200, response.text
        return [run["id"] for run in response.json()]

    newest = page("limit=3")
    assert newest == ids[4:]
    older = page(f"limit=3&before={newest[0]}")
    assert older == ids[1:4]
    assert page(f"limit=3&before={older[0]}") == ids[:1]  # shorter: nothing before it
    assert page(f"before={ids[2]}") == ids[:2]
    assert page("limit=3&before=1") == []
    for bad in ("limit=0", "limit=1001", "before=0", "before=2147483648"):
        refused = client.get(f"/api/runs?{bad}", headers=OPERATOR)
        assert refused.status_code == 422 and refused.json()["detail"][0]["loc"][0] == "query"

"""A paid study of a hundred people through one invite link, over the real API: some join again
from a second browser, some answer a practice pair and take it back, some leave in mid-round,
and one hammers joining and leasing. At the end the budget paid for real answers only, nobody
holds a valid code they did not earn, every honest participant holds one (those left with
nothing to label after the invite's wait included), the participants CSV pays exactly them,
and gold pairs came in the order of the rest, each newcomer's first checks drawn apart."""

from __future__ import annotations

import csv
import io
import time
from dataclasses import dataclass, field
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, SECRET_RETURNS, bearer
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    Query,
    Run,
    claim_run,
    make_engine,
    push_queries,
    session_factory,
    set_clips,
)
from labelqueue.models import utcnow
from server.app import create_app
from server.settings import Settings

PEOPLE = 100
TARGET = 3
REJOIN, UNDO, LEAVE = range(0, 10), range(10, 20), range(20, 30)
"""which participants join again from a second browser, take a practice answer back, leave"""


@dataclass
class Person:
    pid: str
    token: str | None = None
    served: list[tuple[int, bool]] = field(default_factory=list)
    """(query id, practice) in the order shown"""
    real: int = 0
    rejoined: bool = False
    undone: bool = False
    gone: bool = False
    done: bool = False


class Clock:
    """The rate limits' clock: a simulated second per turn of the crowd."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def study_run(client: TestClient, session: Session, settings: Settings) -> tuple[int, set[int]]:
    """A human-taught run with 2 practice pairs, k = 2, gold pairs among 80 ordinary ones, all
    rendered; (run id, gold ids)."""
    run = client.post("/api/runs", headers=OPERATOR, json={
        "task": "dmc:cheetah_run", "algo": "pebble", "budget": 1000, "preset": "tiny",
        "config": {"feedback.practice_pairs": 2, "feedback.labels_per_query": 2,
                   "feedback.gold_rate": 0.2}}).json()
    assert claim_run(session, worker_id="w") is not None
    specs: list[dict[str, Any]] = []
    for position in range(90):
        gold = position in (3, 7) or position % 12 == 5
        specs.append({"round": 0, "position": position, "segment_length": 50,
                      "first_trajectory": 2 * position, "first_start": 10,
                      "second_trajectory": 2 * position + 1, "second_start": 20,
                      **SECRET_RETURNS, **({"gold": True} if gold else {"needs_labels": 2})})
    ids = push_queries(session, run_id=run["id"], queries=specs)
    for query_id in ids:
        keys = [f"run{run['id']}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            (settings.clips_root / key).parent.mkdir(parents=True, exist_ok=True)
            (settings.clips_root / key).write_bytes(b"mp4 " * 50)
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    return run["id"], {i for i, s in zip(ids, specs, strict=True) if s.get("gold")}


def test_a_hundred_participants(settings: Settings) -> None:
    # Leases of a second: a leaver's pair is free again after the one wait below.
    # The server's own rate limits (the fixture lifts them for other tests' scripted labellers).
    limits = {name: Settings.model_fields[name].default for name in ("lease_per_s", "lease_burst")}
    tuned = settings.model_copy(update={"lease_seconds": 1.0} | limits)
    with TestClient(create_app(tuned)) as client:
        engine = make_engine(tuned.database_url)
        with session_factory(engine)() as session:
            crowd(client, session, tuned)
        engine.dispose()


def crowd(client: TestClient, session: Session, settings: Settings) -> None:
    clock = Clock()
    client.app.state.join_limit.clock = clock  # type: ignore[attr-defined]
    client.app.state.lease_limit.clock = clock  # type: ignore[attr-defined]
    run_id, gold = study_run(client, session, settings)
    invite = client.post("/api/invites", headers=OPERATOR, json={
        "run_id": run_id, "target_answers": TARGET, "completion_code": "SIM",
        "wait_limit_s": 1}).json()
    code = invite["code"]
    people = [Person(f"P{i:03d}") for i in range(PEOPLE)]

    def join(person: Person) -> bool:
        response = client.post(f"/api/join/{code}", json={"participant": person.pid})
        if response.status_code == 429:  # the hammerer spent the link's burst: wait, again
            assert int(response.headers["retry-after"]) >= 1
            return False
        assert response.status_code == 201, response.text
        person.token = response.json()["token"]
        return True

    def step(person: Person) -> bool:
        """One action of an honest participant; whether anything changed."""
        if person.token is None:
            join(person)
            return True  # joined, or waits as Retry-After says
        headers = bearer(person.token)
        shown = client.get("/api/label/next", headers=headers)
        if shown.status_code == 204:
            status = client.get("/api/label/status", headers=headers).json()
            person.done = status["progress"]["complete"]
            return person.done
        assert shown.status_code == 200, shown.text
        query = shown.json()
        practice = query["practice"] is not None
        index = int(person.pid[1:])
        if index in LEAVE and person.real == 1:
            person.gone = True  # leaves mid-round, holding the pair on screen
            return True
        body = {"choice": "left", "left_is_first": query["left_is_first"],
                "shown_at": utcnow().isoformat()}
        answered = client.post(f"/api/label/{query['query_id']}", headers=headers, json=body)
        assert answered.status_code == 201, answered.text
        if practice and index in UNDO and not person.undone:
            back = client.post(f"/api/label/{query['query_id']}/withdraw", headers=headers,
                               json={})
            assert back.status_code == 200 and back.json()["query"]["practice"] is not None
            person.undone = True
            return True  # the same practice pair comes again
        person.served.append((query["query_id"], practice))
        person.real += not practice
        if index in REJOIN and person.real == 1 and not person.rejoined:
            old = person.token
            if join(person):  # a second browser: the same labeller, the first signed out
                assert client.get("/api/label/progress", headers=bearer(old)).status_code == 401
                person.rejoined = True
        progress = client.get("/api/label/progress", headers=bearer(person.token)).json()
        person.done = progress["complete"]
        return True

    # The hammerer: one link holder leasing and joining as fast as a script can.
    hammer = client.post(f"/api/join/{code}", json={"participant": "HAMMER"})
    assert hammer.status_code == 201
    refused_leases = sum(client.get("/api/label/next", headers=bearer(
        hammer.json()["token"])).status_code == 429 for _ in range(40))
    rejoins = {client.post(f"/api/join/{code}", json={"participant": "HAMMER"}).json().get(
        "labeller_id") for _ in range(10)}
    refused_joins = sum(client.post(f"/api/join/{code}", json={}).status_code == 429
                        for _ in range(40))
    assert refused_joins >= 10 and refused_leases >= 10
    assert rejoins <= {hammer.json()["labeller_id"], None}  # the same labeller, or a 429

    for _ in range(4):
        moved = True
        while moved:
            moved = False
            for person in people:
                if not (person.done or person.gone):
                    clock.now += 0.5
                    moved |= step(person)
        if all(p.done or p.gone for p in people):
            break
        time.sleep(1.1)  # those with nothing to label wait the invite's limit, asking

    honest = {p.pid for p in people if not p.gone}
    assert all(p.done for p in people if not p.gone)

    # The budget paid for real answers only: no practice, no gold.
    with session.begin():
        used = session.scalar(select(Run.labels_used).where(Run.id == run_id))
        real = session.scalar(select(func.count()).select_from(Label).join(
            Query, Query.id == Label.query_id).where(
            Label.run_id == run_id, Label.withdrawn_at.is_(None), Query.gold.is_(False)))
        practice = session.scalar(select(func.count()).select_from(Label).where(
            Label.practice.is_(True), Label.withdrawn_at.is_(None)))
    assert used == real and practice == 2 * PEOPLE  # everyone practised both pairs
    # One labeller per participant id: no extra slot for second browsers.
    rows = client.get(f"/api/invites/{invite['id']}/participants", headers=OPERATOR).json()
    by_pid = {r["participant"]: r for r in rows if r["participant"]}
    assert len(by_pid) == sum(1 for r in rows if r["participant"])
    # Nobody holds a valid code they did not earn; every honest participant holds one.
    for row in rows:
        if row["code_valid"]:
            assert row["counted"] >= TARGET or row["why"] == "nothing_left", row
    text = client.get(f"/api/invites/{invite['id']}/participants?format=csv",
                      headers=OPERATOR).text
    paid = {r["participant"] for r in csv.DictReader(io.StringIO(text))
            if r["code_valid"] == "True"}
    assert paid == honest
    assert any(by_pid[pid]["why"] == "nothing_left" for pid in honest)

    # Gold pairs come in the order of the rest: each is above every pair served before it.
    firsts = []
    for person in people:
        real_ids = [q for q, practice in person.served if not practice]
        checks = [n for n, query_id in enumerate(real_ids) if query_id in gold]
        for n in checks:
            assert all(real_ids[n] > before for before in real_ids[:n])
        firsts += [real_ids[n] for n in checks[:1]]
    assert len(set(firsts)) > 1  # not one pair everyone's first check

"""Taking an answer back: within 10 s and while the trainer has not taken it, the answer is
withdrawn (kept, and shown in the export), the pair comes back to the labeller, the run gets
its budget back and the trainer never reads it; too late, consumed, or not yours is refused
plainly; bad requests are 4xx naming the problem."""

from __future__ import annotations

import json
from datetime import timedelta
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, running_run_with_queries
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    consume_labels,
    labels_for_queries,
    read_run,
    settled,
)
from labelqueue.models import utcnow
from server.settings import Settings


def answer(client: TestClient, token: str, run_id: int, choice: str = "left") -> int:
    nxt = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    body = {"choice": choice, "left_is_first": nxt["left_is_first"],
            "shown_at": "2026-01-01T00:00:00Z"}
    response = client.post(f"/api/label/{nxt['query_id']}", json=body, headers=bearer(token))
    assert response.status_code == 201, response.text
    query_id: int = nxt["query_id"]
    return query_id


def withdraw(client: TestClient, token: str, query_id: int, **body: Any) -> Any:
    return client.post(f"/api/label/{query_id}/withdraw", json=body, headers=bearer(token))


def export(client: TestClient, run_id: int) -> list[dict[str, Any]]:
    response = client.get(f"/api/export?format=jsonl&run_id={run_id}", headers=OPERATOR)
    return [json.loads(line) for line in response.text.splitlines()]


def test_an_answer_taken_back_is_kept_withdrawn_and_its_pair_comes_back(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "alice")
    run_id, ids = running_run_with_queries(client, session, settings, n=3)
    first = answer(client, token, run_id, "left")
    # The page preloads the next pair, then the labeller takes the first answer back.
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    ahead = client.get(f"/api/label/next?run_id={run_id}&ahead_of={shown['query_id']}",
                       headers=bearer(token)).json()
    assert read_run(session, run_id=run_id).labels_used == 1

    response = withdraw(client, token, first, keep=shown["query_id"])
    assert response.status_code == 200, response.text
    back = response.json()
    assert back["query"]["query_id"] == first  # the pair, to show again, with fresh clip URLs
    assert back["query"]["left_clip_url"].startswith(f"/api/clips/{first}/")
    assert "first_segment_return" not in json.dumps(back)
    # The budget comes back; the trainer reads no label of the query.
    assert read_run(session, run_id=run_id).labels_used == 0
    assert labels_for_queries(session, query_ids=[first]) == []
    # The pair on screen is kept, the preloaded one released for others.
    bob = new_labeller(client, "bob")
    assert client.get(f"/api/label/next?run_id={run_id}",
                      headers=bearer(bob)).json()["query_id"] == ahead["query_id"]
    again = client.get(f"/api/label/next?run_id={run_id}&ahead_of={first}",
                       headers=bearer(token)).json()
    assert again["query_id"] == shown["query_id"]

    # Answered again: a new label beside the withdrawn one; the export shows both.
    nxt_body = {"choice": "right", "left_is_first": back["query"]["left_is_first"],
                "shown_at": "2026-01-01T00:00:00Z"}
    assert client.post(f"/api/label/{first}", json=nxt_body,
                       headers=bearer(token)).status_code == 201
    rows = [row for row in export(client, run_id) if row["query_id"] == first]
    assert [(row["choice"], row["withdrawn_at"] is not None) for row in rows] == [
        ("left", True), ("right", False)]
    [standing] = labels_for_queries(session, query_ids=[first])
    assert standing.choice == "right"
    assert [label.query_id for label in consume_labels(session, run_id=run_id)] == [first]
    # Taking it back twice: the second answer can be; the first is already withdrawn.
    assert withdraw(client, token, first).status_code == 409  # the trainer took it


def test_undo_says_plainly_when_it_is_too_late_or_the_trainer_has_the_answer(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "alice")
    run_id, _ = running_run_with_queries(client, session, settings, n=3)
    late = answer(client, token, run_id)
    with session.begin():
        session.execute(update(Label).where(Label.query_id == late)
                        .values(answered_at=utcnow() - timedelta(seconds=25)))
    response = withdraw(client, token, late)
    assert response.status_code == 409
    assert "given 25 s ago" in response.json()["detail"]
    assert "10 s only" in response.json()["detail"]

    taken = answer(client, token, run_id)
    consume_labels(session, run_id=run_id)
    response = withdraw(client, token, taken)
    assert response.status_code == 409
    assert "trainer has already taken" in response.json()["detail"]
    # Nothing changed by a refusal.
    assert len(labels_for_queries(session, query_ids=[late, taken])) == 2
    assert read_run(session, run_id=run_id).labels_used == 2

    stopped = answer(client, token, run_id)
    assert client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).status_code == 200
    response = withdraw(client, token, stopped)
    assert response.status_code == 409 and "answer stands" in response.json()["detail"]


def test_only_your_own_standing_answer_is_taken_back_and_bad_requests_are_4xx(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice, bob = new_labeller(client, "alice"), new_labeller(client, "bob")
    run_id, ids = running_run_with_queries(client, session, settings, n=2)
    mine = answer(client, alice, run_id)
    response = withdraw(client, bob, mine)
    assert response.status_code == 404 and "no answer to query" in response.json()["detail"]
    assert withdraw(client, alice, ids[1]).status_code == 404  # not answered
    assert withdraw(client, alice, 999).status_code == 404
    assert withdraw(client, alice, 0).status_code == 422
    assert withdraw(client, alice, 2**31).status_code == 422
    for body in ({"keep": 0}, {"keep": "x"}, {"keep": 2**31}, {"other": 1}):
        response = withdraw(client, alice, mine, **body)
        assert response.status_code == 422, body
        assert any(next(iter(body)) in error["loc"] for error in response.json()["detail"])
    assert client.post(f"/api/label/{mine}/withdraw").status_code == 401
    assert client.post(f"/api/label/{mine}/withdraw", headers=OPERATOR).status_code == 403
    assert client.get(f"/api/label/{mine}/withdraw", headers=bearer(alice)).status_code == 405
    # None of that changed anything: alice can still take her answer back.
    assert withdraw(client, alice, mine).status_code == 200


def test_the_trainer_waits_until_an_answer_can_no_longer_be_taken_back() -> None:
    now = utcnow()
    assert not settled(now - timedelta(seconds=9), now)
    assert not settled(now - timedelta(seconds=12), now)  # a margin for clocks
    assert settled(now - timedelta(seconds=16), now)

"""Flags over the API: a skip may carry a flag and a note; a flag on any other answer, an
unknown flag or an overlong note is a 422 naming the problem; the run's flags are counted for
its operator (GET /api/runs/{id}/flags), for no one else, and a 404 for an unknown run."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, running_run_with_queries
from sqlalchemy.orm import Session

from server.settings import Settings

SHOWN_AT = "2026-01-01T00:00:00Z"


def post(client: TestClient, token: str, query_id: int, **body: Any) -> Any:
    return client.post(f"/api/label/{query_id}", json={"shown_at": SHOWN_AT} | body,
                       headers=bearer(token))


def test_a_flagged_skip_is_stored_and_counted(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "alice")
    run_id, _ = running_run_with_queries(client, session, settings, 2)
    nxt = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    qid = nxt["query_id"]

    for body, words in (
        ({"choice": "left", "flag": "other"}, "send choice 'skip' with the flag"),
        ({"choice": "skip", "flag": "ugly"}, "flag"),
        ({"choice": "skip", "flag": "other", "flag_note": "x" * 501}, "flag_note"),
        ({"choice": "skip", "flag_note": "why"}, "flag_note needs a flag"),
    ):
        response = post(client, token, qid, **body)
        assert response.status_code == 422, response.text
        assert words in response.text, response.text

    response = post(client, token, qid, choice="skip", flag="clip_broken",
                    flag_note="stops after a few frames")
    assert response.status_code == 201, response.text
    label = response.json()
    assert (label["answer"], label["flag"], label["flag_note"]) == (
        "skip", "clip_broken", "stops after a few frames")

    flags = client.get(f"/api/runs/{run_id}/flags", headers=OPERATOR)
    assert flags.status_code == 200, flags.text
    summary = flags.json()
    assert summary["total"] == 1 and summary["by_flag"]["clip_broken"] == 1
    [latest] = summary["latest"]
    assert (latest["query_id"], latest["labeller_name"], latest["note"]) == (
        qid, "alice", "stops after a few frames")
    # Operators only; an unknown run is a 404.
    assert client.get(f"/api/runs/{run_id}/flags", headers=bearer(token)).status_code == 403
    assert client.get("/api/runs/999/flags", headers=OPERATOR).status_code == 404

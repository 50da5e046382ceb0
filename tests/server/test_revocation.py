"""Revoking a labeller or giving them a new token takes effect at once, from any process: the
command line's change reaches a running server's lease, answer and undo although the server
trusts the checked token for a few seconds (`SEPOA_AUTH_CACHE_SECONDS`)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from server_helpers import bearer, new_labeller, running_run_with_queries, snapshot
from sqlalchemy.orm import Session

import server.deps
from labelqueue import set_labeller_active
from sepoa.cli import main
from server.settings import Settings

SHOWN = "2026-01-01T00:00:00Z"


def _next(client: TestClient, token: str, run_id: int):  # type: ignore[no-untyped-def]
    return client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token))


def _answer(client: TestClient, token: str, query: dict):  # type: ignore[no-untyped-def]
    body = {"choice": "left", "left_is_first": query["left_is_first"], "shown_at": SHOWN}
    return client.post(f"/api/label/{query['query_id']}", json=body, headers=bearer(token))


def _withdraw(client: TestClient, token: str, query_id: int):  # type: ignore[no-untyped-def]
    return client.post(f"/api/label/{query_id}/withdraw", json={}, headers=bearer(token))


def test_a_new_token_made_by_the_cli_stops_the_old_one_at_once(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    old = new_labeller(client, "alice")
    shown = _next(client, old, run_id).json()  # the server has checked the token: cached
    assert _answer(client, old, shown).status_code == 201
    held = _next(client, old, run_id).json()
    assert main(["labeller", "token", "alice", "--data-dir", str(settings.data_dir)]) == 0
    before = snapshot(session)
    for refused in (_next(client, old, run_id), _answer(client, old, held),
                    _withdraw(client, old, shown["query_id"])):
        assert refused.status_code == 401, refused.text
        assert "replaced by a new one" in refused.json()["detail"]
        assert refused.headers["www-authenticate"] == "Bearer"
    assert snapshot(session) == before  # nothing leased, answered or taken back


def test_a_labeller_revoked_by_the_cli_cannot_take_an_answer_back(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=4)
    token = new_labeller(client, "bob")
    shown = _next(client, token, run_id).json()
    assert _answer(client, token, shown).status_code == 201
    assert main(["labeller", "revoke", "bob", "--data-dir", str(settings.data_dir)]) == 0
    before = snapshot(session)
    taken_back = _withdraw(client, token, shown["query_id"])  # within the undo window
    assert taken_back.status_code == 403, taken_back.text
    assert "deactivated" in taken_back.json()["detail"]
    assert _next(client, token, run_id).status_code == 403
    assert snapshot(session) == before  # the answer stands; no pair leased to bob again


def test_an_operator_revoked_by_the_cli_loses_every_operator_right_at_once(
    client: TestClient, settings: Settings
) -> None:
    boss = bearer(new_labeller(client, "boss", role="operator"))
    assert client.get("/api/labellers", headers=boss).status_code == 200  # token checked
    assert main(["labeller", "revoke", "boss", "--data-dir", str(settings.data_dir)]) == 0
    made = client.post("/api/labellers", json={"name": "backdoor", "role": "operator"},
                       headers=boss)
    assert made.status_code == 401, made.text
    restored = client.patch("/api/labellers/1", json={"active": True}, headers=boss)
    assert restored.status_code == 401, restored.text
    assert client.get("/api/labellers", headers=boss).status_code == 401


def test_a_revoke_landing_during_a_token_check_is_not_undone_by_the_cache(
    client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    token = new_labeller(client, "carol")
    labeller_id = int(token.split(".")[0])
    read = server.deps.authenticate
    cache = client.app.state.token_cache  # type: ignore[attr-defined]

    def revoked_after_the_read(db: Session, *, token: str):  # type: ignore[no-untyped-def]
        row = read(db, token=token)
        set_labeller_active(session, labeller_id=labeller_id, active=False)  # what PATCH does
        cache.forget(labeller_id)
        return row

    monkeypatch.setattr(server.deps, "authenticate", revoked_after_the_read)
    assert client.get("/api/label/count", headers=bearer(token)).status_code == 200  # in flight
    monkeypatch.setattr(server.deps, "authenticate", read)
    assert client.get("/api/label/count", headers=bearer(token)).status_code == 401

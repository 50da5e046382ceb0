"""A run created over REST stores the configuration it trains with; `GET /api/runs/{id}/config`
shows it, the run's own settings marked, and a bad field is refused before anything is
stored."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, new_run
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import Run, claim_run, finish_run, read_run
from labelqueue.run_config import run_config
from runvocab.config import PRESETS


def test_a_run_created_over_rest_stores_and_shows_what_it_trains(
        client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    run = new_run(client, config={"sac.lr": 0.001}, teacher_params={"eps": 0.2})
    stored = read_run(session, run_id=run["id"])
    assert stored.resolved_config is not None
    assert run_config(stored).sac.lr == 0.001
    assert run_config(stored).sac.hidden_dim == PRESETS["tiny"]["sac.hidden_dim"]

    monkeypatch.setitem(PRESETS, "tiny", PRESETS["tiny"] | {"sac.hidden_dim": 8})
    shown = client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR)
    assert shown.status_code == 200, shown.text
    body = shown.json()
    assert body["stored"] is True
    assert body["values"]["sac.hidden_dim"] == 32  # as stored, whatever the preset says now
    assert body["values"]["sac.lr"] == 0.001
    assert body["values"]["feedback.selection"] == "skill"  # S-EPOA's algorithm preset
    assert body["values"]["teacher.beta"] == "inf"
    assert sorted(body["overridden"]) == ["sac.lr", "teacher.eps"]


def test_a_run_stored_without_its_configuration_shows_it_resolved_now(
        client: TestClient, session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    run = new_run(client)
    session.execute(update(Run).where(Run.id == run["id"]).values(resolved_config=None))
    session.commit()
    monkeypatch.setitem(PRESETS, "tiny", PRESETS["tiny"] | {"sac.hidden_dim": 8})
    body = client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR).json()
    assert (body["stored"], body["values"]["sac.hidden_dim"]) == (False, 8)

    session.execute(update(Run).where(Run.id == run["id"]).values(config={"steps": "many"}))
    session.commit()
    refused = client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR)
    assert refused.status_code == 409
    assert "'steps' takes int" in refused.json()["detail"]
    assert client.get("/api/runs/999/config", headers=OPERATOR).status_code == 404


def test_a_bad_field_is_refused_at_the_field_and_nothing_is_stored(
        client: TestClient) -> None:
    body = {"task": "dmc:cheetah_run", "algo": "pebble", "budget": 10, "preset": "tiny"}
    refused = client.post("/api/runs", json=body | {"config": {"reward.surf": "flase"}},
                          headers=OPERATOR)
    assert refused.status_code == 422
    assert refused.json()["detail"][0]["loc"] == ["body", "config", "reward.surf"]
    refused = client.post("/api/runs", json=body | {"teacher_params": {"eps": "x"}},
                          headers=OPERATOR)
    assert refused.json()["detail"][0]["loc"] == ["body", "teacher_params", "eps"]
    assert client.get("/api/runs", headers=OPERATOR).json() == []


def test_a_teacher_switch_changes_the_stored_teacher(client: TestClient, session: Session) -> None:
    run = new_run(client, teacher_params={"eps": 0.2})
    switched = client.put(f"/api/runs/{run['id']}/teacher", headers=OPERATOR,
                          json={"teacher": "scripted", "params": {"eps": 0.4}})
    assert switched.status_code == 200, switched.text
    assert run_config(read_run(session, run_id=run["id"])).teacher.eps == 0.4
    refused = client.put(f"/api/runs/{run['id']}/teacher", headers=OPERATOR,
                         json={"teacher": "scripted", "params": {"eps": "x"}})
    assert refused.status_code == 422
    assert refused.json()["detail"][0]["loc"] == ["body", "params", "eps"]
    assert run_config(read_run(session, run_id=run["id"])).teacher.eps == 0.4


@pytest.mark.parametrize("end", ["finished", "failed", "stopped", "stopping"])
def test_a_run_no_worker_asks_again_keeps_the_teacher_it_had(
        client: TestClient, session: Session, end: str) -> None:
    run = new_run(client, teacher="scripted", teacher_params={"eps": 0.1})
    assert claim_run(session, worker_id="w") is not None
    if end == "stopping":
        client.post(f"/api/runs/{run['id']}/stop", headers=OPERATOR)
    else:
        finish_run(session, run_id=run["id"], worker_id="w", status=end)
    before = client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR).json()
    refused = client.put(f"/api/runs/{run['id']}/teacher", headers=OPERATOR,
                         json={"teacher": "human", "params": {"eps": 0.3}})
    assert refused.status_code == 409, refused.text
    assert f"run {run['id']} is {end}" in refused.json()["detail"]
    stored = read_run(session, run_id=run["id"])
    assert (stored.teacher, stored.teacher_params) == ("scripted", {"eps": 0.1})
    assert client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR).json() == before
    assert before["values"]["teacher.eps"] == 0.1


def test_a_switch_gives_a_new_eps_to_a_run_whose_config_set_it(
        client: TestClient, session: Session) -> None:
    run = new_run(client, teacher="scripted", config={"teacher.eps": 0.2, "sac.lr": 0.001})
    switched = client.put(f"/api/runs/{run['id']}/teacher", headers=OPERATOR,
                          json={"teacher": "scripted", "params": {"eps": 0.1}})
    assert switched.status_code == 200, switched.text
    # The parameters take the config's place: the run holds the eps once, the new one.
    assert switched.json()["config"] == {"sac.lr": 0.001}
    assert switched.json()["teacher_params"] == {"eps": 0.1}
    shown = client.get(f"/api/runs/{run['id']}/config", headers=OPERATOR).json()
    assert (shown["values"]["teacher.eps"], shown["values"]["sac.lr"]) == (0.1, 0.001)
    assert sorted(shown["overridden"]) == ["sac.lr", "teacher.eps"]
    # A switch that leaves eps out keeps the config's: only what `params` names is replaced.
    other = new_run(client, name="other", config={"teacher.eps": 0.2})
    kept = client.put(f"/api/runs/{other['id']}/teacher", headers=OPERATOR,
                      json={"teacher": "scripted", "params": {}})
    assert kept.status_code == 200 and kept.json()["config"] == {"teacher.eps": 0.2}
    assert run_config(read_run(session, run_id=other["id"])).teacher.eps == 0.2

"""What an operator and a labeller are told about waiting: a run's activity (a free worker,
pretraining with an estimate, N answers from K active labellers), the label page's reason, the
workers with their heartbeats, a new run's defaults (the preset's budget, the clip length,
S-EPOA's pretraining estimate), and links made with the server's public URL."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

from fastapi.testclient import TestClient
from server_helpers import (
    OPERATOR,
    bearer,
    new_labeller,
    new_run,
    query_spec,
    running_run_with_queries,
)
from sqlalchemy import update
from sqlalchemy.orm import Session

from labelqueue import (
    LabellerPause,
    Worker,
    claim_run,
    create_labeller,
    heartbeat,
    make_engine,
    push_queries,
    session_factory,
    set_clips,
)
from labelqueue.models import utcnow
from server.app import create_app
from server.settings import Settings


def test_a_run_says_it_waits_for_answers_from_paused_labellers_and_for_a_free_worker(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=10)
    token = new_labeller(client, "ann")
    ann = client.get("/api/labellers", headers=OPERATOR).json()[-1]["id"]
    session.add(LabellerPause(run_id=run_id, labeller_id=ann, gold_answers=3, gold_correct=0))
    session.commit()
    activity = client.get(f"/api/runs/{run_id}/activity", headers=OPERATOR).json()
    assert activity["phase"] == "labelling"
    assert activity["text"] == ("waiting for 10 answers from 0 active labellers (1 paused by "
                                "check pairs)")
    assert (activity["answers_needed"], activity["labellers_paused"]) == (10, 1)
    assert client.get(f"/api/runs/{run_id}/activity", headers=bearer(token)).status_code == 403

    # Another run waits for a worker: the only one is busy with the first.
    queued = new_run(client)["id"]
    waiting = client.get(f"/api/runs/{queued}/activity", headers=OPERATOR).json()
    assert waiting["phase"] == "queued"
    assert waiting["text"] == "waiting for a free worker: 1 worker alive, all busy"
    with session.begin():
        session.execute(update(Worker).values(last_seen_at=utcnow() - timedelta(minutes=10)))
    gone = client.get(f"/api/runs/{queued}/activity", headers=OPERATOR).json()
    assert gone["text"].startswith("waiting for a worker: none is running")
    [worker] = client.get("/api/workers", headers=OPERATOR).json()
    assert (worker["id"], worker["run_id"], worker["state"]) == ("worker-1", run_id, "dead")
    assert worker["host"] and worker["silent_s"] > 500
    assert client.get("/api/workers", headers=bearer(token)).status_code == 403
    assert client.get("/api/runs/999/activity", headers=OPERATOR).status_code == 404


def test_the_scripted_teacher_is_listed_as_no_person(client: TestClient, session: Session) -> None:
    create_labeller(session, name="scripted-teacher")  # as the first worker makes it
    new_labeller(client, "dee")
    listed = {who["name"]: who["scripted"] for who in
              client.get("/api/labellers", headers=OPERATOR).json()}
    assert listed["scripted-teacher"] is True and listed["dee"] is False


def test_the_label_page_is_told_why_nothing_is_there(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "bea")
    status = client.get("/api/label/status", headers=bearer(token)).json()
    assert status["waiting"]["reason"] == "no_run"
    assert status["progress"]["invited"] is False

    run_id = new_run(client)["id"]
    assert claim_run(session, worker_id="worker-2") is not None
    heartbeat(session, run_id=run_id, worker_id="worker-2", step=0,
              progress={"pretraining_step": 3000, "pretraining_steps": 30_000,
                        "pretraining_fps": 90.0})
    waiting = client.get(f"/api/label/status?run_id={run_id}", headers=bearer(token)).json()
    assert waiting["waiting"]["reason"] == "pretraining"
    assert waiting["waiting"]["eta_s"] == 300.0
    assert waiting["waiting"]["text"] == ("The trainer is first pretraining its skills, before "
                                          "it asks anything: about 5 min left.")
    heartbeat(session, run_id=run_id, worker_id="worker-2", step=600,
              progress={"fps": 100.0, "next_round_step": 2600, "episode": 3})
    exploring = client.get(f"/api/label/status?run_id={run_id}", headers=bearer(token)).json()
    assert exploring["waiting"]["reason"] == "exploring" and exploring["waiting"]["eta_s"] == 20
    assert "about 20 s" in exploring["waiting"]["text"]
    assert client.get("/api/label/status?run_id=0", headers=bearer(token)).status_code == 422


def test_the_defaults_refuse_what_a_new_run_is_refused_naming_the_field(
    client: TestClient,
) -> None:
    for config, field in (('{"feedback.budget": -5}', "feedback.budget"),
                          ('{"feedback.segment_length": 0}', "feedback.segment_length"),
                          ('{"sac.lr": NaN}', "sac.lr")):
        shown = client.get("/api/runs/defaults", headers=OPERATOR,
                           params={"task": "dmc:cheetah_run", "config": config})
        assert shown.status_code == 422, (config, shown.text)
        assert shown.json()["detail"][0]["loc"] == ["query", "config", field]
        assert field in shown.json()["detail"][0]["msg"]
    deep = client.get("/api/runs/defaults", headers=OPERATOR,
                      params={"task": "dmc:cheetah_run", "config": "[" * 5000 + "]" * 5000})
    assert deep.status_code == 422, deep.text
    assert deep.json()["detail"][0]["loc"] == ["query", "config"]
    assert "JSON object" in deep.json()["detail"][0]["msg"]


def test_a_new_run_defaults_to_its_presets_budget_and_the_form_learns_the_clip_length(
    client: TestClient,
) -> None:
    tiny = client.get("/api/runs/defaults?task=dmc:cheetah_run&algo=pebble&preset=tiny",
                      headers=OPERATOR).json()
    assert (tiny["budget"], tiny["segment_length"], tiny["pretrain_steps"]) == (30, 20, 0)
    assert tiny["clip_seconds"] == 0.6 and tiny["task_seconds"] == 0.2
    assert tiny["first_round_steps"] == 400
    small = client.get("/api/runs/defaults?task=dmc:cheetah_run&algo=sepoa&preset=small",
                       headers=OPERATOR).json()
    assert small["pretrain_steps"] == 200_000 and small["pretrain_pace_measured"] is False
    assert 600 < small["pretrain_seconds"] < 1200  # about a quarter of an hour on 2 cores
    assert small["segment_length"] == 60 and small["budget"] == 1000
    bad = client.get("/api/runs/defaults?task=dmc:cheetah_run&config=%7B%22nope%22%3A1%7D",
                     headers=OPERATOR)
    assert bad.status_code == 422 and "nope" in bad.text
    assert client.get("/api/runs/defaults?task=cheetah", headers=OPERATOR).status_code == 422

    made = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                          "preset": "tiny"}, headers=OPERATOR)
    assert made.status_code == 201 and made.json()["budget"] == 30
    told = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                          "preset": "tiny", "config": {"feedback.budget": 12}},
                       headers=OPERATOR)
    assert told.status_code == 201 and told.json()["budget"] == 12
    # A config value as text is read as any config value is: the budget it gives, not a
    # contradiction of a top-level field the caller never sent.
    text = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                          "preset": "tiny", "config": {"feedback.budget": "500"}},
                       headers=OPERATOR)
    assert text.status_code == 201 and text.json()["budget"] == 500, text.text
    bad = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                         "preset": "tiny", "config": {"feedback.budget": "lots"}},
                      headers=OPERATOR)
    assert bad.status_code == 422 and bad.json()["detail"][0]["loc"][-1] == "feedback.budget"
    for field, value in (("seed", False), ("seed", 1.5), ("budget", True), ("budget", "12")):
        wrong = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                               "preset": "tiny", field: value},
                            headers=OPERATOR)
        assert wrong.status_code == 422 and wrong.json()["detail"][0]["loc"] == ["body", field]
    # JSON Schema's integer: 12.0 is one.
    whole = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                           "preset": "tiny", "seed": 7.0, "budget": 12.0},
                        headers=OPERATOR).json()
    assert (whole["seed"], whole["budget"]) == (7, 12)


def test_invite_and_clip_links_use_the_public_url(tmp_path: Path) -> None:
    data = tmp_path / "public"
    settings = Settings(database_url=f"sqlite:///{data / 'queue.db'}", data_dir=data,
                        operator_token="public-operator-token-0123",
                        secret_key="test-secret-key-0123456789",
                        public_url="https://label.example.org/sepoa/")
    assert settings.public_url == "https://label.example.org/sepoa"
    with TestClient(create_app(settings)) as client:
        engine = make_engine(settings.database_url)
        with session_factory(engine)() as session:
            operator = {"Authorization": "Bearer public-operator-token-0123"}
            invite = client.post("/api/invites", json={}, headers=operator).json()
            assert invite["url"] == f"https://label.example.org/sepoa/join/{invite['code']}"
            body = {"task": "dmc:cheetah_run", "algo": "pebble", "preset": "tiny"}
            run_id = client.post("/api/runs", json=body, headers=operator).json()["id"]
            assert claim_run(session, worker_id="w") is not None
            [query_id] = push_queries(session, run_id=run_id, queries=[query_spec(0)])
            set_clips(session, query_id=query_id, first_clip="a.mp4", second_clip="b.mp4")
            token = client.post("/api/labellers", json={"name": "cy"},
                                headers=operator).json()["token"]
            shown = client.get("/api/label/next", headers=bearer(token)).json()
            assert shown["left_clip_url"].startswith(
                f"https://label.example.org/sepoa/api/clips/{query_id}/")
        engine.dispose()
    for bad in ("label.example.org", "ftp://x.org", "https://x.org/?a=1"):
        try:
            Settings(public_url=bad)
        except ValueError as err:
            assert "public_url" in str(err)
        else:
            raise AssertionError(bad)

"""The operator's REST API: runs, their controls and curves, labellers; auth and bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, OPERATOR_TOKEN, bearer, new_labeller, new_run, snapshot
from sqlalchemy.orm import Session

from labelqueue import (
    Run,
    RunStatus,
    claim_run,
    find_labeller,
    make_engine,
    session_factory,
    sqlite_url,
    write_metrics,
)
from server.app import create_app
from server.settings import Settings, get_settings


def stored_run(session: Session, run_id: int) -> Run:
    run = session.get(Run, run_id, populate_existing=True)
    session.commit()
    assert run is not None
    return run


def test_health_and_openapi_list_the_api(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    paths = set(client.get("/openapi.json").json()["paths"])
    assert {
        "/api/runs",
        "/api/runs/{run_id}",
        "/api/runs/{run_id}/metrics",
        "/api/runs/{run_id}/pause",
        "/api/runs/{run_id}/resume",
        "/api/runs/{run_id}/stop",
        "/api/runs/{run_id}/teacher",
        "/api/labellers",
        "/api/label/next",
        "/api/label/{query_id}",
        "/api/clips/{query_id}/{side}",
        "/healthz",
    } <= paths


def test_an_operator_creates_lists_and_reads_runs(client: TestClient, session: Session) -> None:
    run = new_run(
        client,
        task="metaworld:drawer-open",
        algo="pebble",
        teacher="scripted",
        teacher_params={"eps": 0.1},
        seed=3,
        budget=500,
        config={"sac.lr": 1e-4},
    )
    assert run["status"] == "queued" and run["name"] == "metaworld:drawer-open-pebble-s3"
    assert run["teacher_params"] == {"eps": 0.1} and run["config"] == {"sac.lr": 1e-4}
    row = stored_run(session, run["id"])
    assert (row.task, row.algo, row.seed, row.budget) == (
        "metaworld:drawer-open",
        "pebble",
        3,
        500,
    )

    listed = client.get("/api/runs", headers=OPERATOR).json()
    assert [r["id"] for r in listed] == [run["id"]]
    status = client.get(f"/api/runs/{run['id']}", headers=OPERATOR).json()
    for key in ("status", "step", "labels_used", "budget", "worker_id", "heartbeat_at", "error"):
        assert key in status


def test_metrics_come_back_by_stream_and_step(client: TestClient, session: Session) -> None:
    run_id = new_run(client)["id"]
    write_metrics(session, run_id=run_id, stream="eval", step=2000, values={"return": 5.0})
    write_metrics(session, run_id=run_id, stream="eval", step=1000, values={"return": 3.0})
    write_metrics(session, run_id=run_id, stream="episodes", step=1000, values={"return": 1.0})
    response = client.get(f"/api/runs/{run_id}/metrics?stream=eval", headers=OPERATOR)
    assert response.json() == [
        {"step": 1000, "values": {"return": 3.0}},
        {"step": 2000, "values": {"return": 5.0}},
    ]
    bad = client.get(f"/api/runs/{run_id}/metrics?stream=losses", headers=OPERATOR)
    assert bad.status_code == 422 and "stream" in bad.json()["detail"][0]["loc"]
    missing = client.get("/api/runs/77/metrics?stream=eval", headers=OPERATOR)
    assert missing.status_code == 404 and "run 77" in missing.json()["detail"]


def test_pause_resume_stop_and_teacher_switch_change_the_run(
    client: TestClient, session: Session
) -> None:
    run_id = new_run(client)["id"]
    assert claim_run(session, worker_id="worker-1") is not None

    def post(action: str) -> dict[str, Any]:
        response = client.post(f"/api/runs/{run_id}/{action}", headers=OPERATOR)
        assert response.status_code == 200, response.text
        body: dict[str, Any] = response.json()
        return body

    assert post("pause")["status"] == "paused"
    assert stored_run(session, run_id).status is RunStatus.PAUSED
    assert post("resume")["status"] == "running"
    assert stored_run(session, run_id).status is RunStatus.RUNNING

    switched = client.put(
        f"/api/runs/{run_id}/teacher",
        json={"teacher": "scripted", "params": {"eps": 0.2}},
        headers=OPERATOR,
    )
    assert switched.status_code == 200 and switched.json()["teacher"] == "scripted"
    row = stored_run(session, run_id)
    assert row.teacher == "scripted" and row.teacher_params == {"eps": 0.2}

    assert post("stop")["status"] == "stopping"
    assert stored_run(session, run_id).status is RunStatus.STOPPING
    assert post("stop?force=true")["status"] == "stopped"
    assert post("requeue")["status"] == "queued"
    assert post("stop")["status"] == "stopped"  # a queued run is cancelled at once
    assert stored_run(session, run_id).status is RunStatus.STOPPED


@pytest.mark.parametrize(
    ("action", "detail"),
    [
        ("resume", "run 1 is queued; it cannot be made running"),
        ("pause", "run 1 is queued; it cannot be made paused"),
        ("requeue", "run 1 is queued; it cannot be made queued"),
    ],
)
def test_an_invalid_transition_is_refused_and_changes_nothing(
    client: TestClient, session: Session, action: str, detail: str
) -> None:
    assert new_run(client)["id"] == 1
    before = snapshot(session)
    response = client.post(f"/api/runs/1/{action}", headers=OPERATOR)
    assert response.status_code == 409 and response.json() == {"detail": detail}
    assert snapshot(session) == before


def test_unknown_runs_are_404_and_change_nothing(client: TestClient, session: Session) -> None:
    new_run(client)
    before = snapshot(session)
    for method, path, body in [
        ("GET", "/api/runs/9", None),
        ("POST", "/api/runs/9/pause", None),
        ("POST", "/api/runs/9/stop", None),
        ("PUT", "/api/runs/9/teacher", {"teacher": "human"}),
    ]:
        response = client.request(method, path, json=body, headers=OPERATOR)
        assert response.status_code == 404, path
        assert response.json() == {"detail": "run 9 does not exist"}
    assert snapshot(session) == before


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ({"task": "cheetah_run"}, "task"),
        ({"task": "dmc:Cheetah Run"}, "task"),
        ({"task": "atari:pong"}, "task"),
        ({"algo": "ppo"}, "algo"),
        ({"budget": -1}, "budget"),
        ({"preset": "huge"}, "preset"),
        ({"teacher": "oracle"}, "teacher"),
        ({"seed": "one"}, "seed"),
        ({"budgett": 5}, "budgett"),
    ],
)
def test_a_malformed_run_is_422_naming_the_field(
    client: TestClient, session: Session, override: dict[str, Any], field: str
) -> None:
    before = snapshot(session)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 0} | override
    response = client.post("/api/runs", json=body, headers=OPERATOR)
    assert response.status_code == 422
    assert any(field in error["loc"] for error in response.json()["detail"]), response.text
    assert snapshot(session) == before


@pytest.mark.parametrize(
    ("override", "loc", "words"),
    [
        ({"task": "dmc:cheetah_runn"}, ["body", "task"], ["did you mean 'dmc:cheetah_run'"]),
        ({"algo": "sepoaa"}, ["body", "algo"], ["did you mean 'sepoa'", "pebble"]),
        ({"preset": "smal"}, ["body", "preset"], ["did you mean 'small'"]),
        ({"config": {"feedback.per_rund": 10}}, ["body", "config", "feedback.per_rund"],
         ["did you mean 'feedback.per_round'"]),
        ({"config": {"sac.lr": "fast"}}, ["body", "config", "sac.lr"], ["takes float"]),
        ({"config": {"reward.surf": "flase"}}, ["body", "config", "reward.surf"],
         ["takes bool, got 'flase'", "true/false, yes/no, on/off or 1/0"]),
        ({"config": {"feedback.budget": 500}}, ["body", "config", "feedback.budget"],
         ["top-level field says 0"]),
        ({"config": {"algo": "pebble"}}, ["body", "config", "algo"], ["says 'sac'"]),
        ({"config": {"run_dir": "/tmp/elsewhere"}}, ["body", "config", "run_dir"], ["worker"]),
        ({"teacher_params": {"eps": 5}}, ["body", "teacher_params", "eps"], ["[0, 1)"]),
        ({"teacher_params": {"eps": 0.1}, "config": {"teacher.eps": 0.2}},
         ["body", "config", "teacher.eps"], ["teacher_params says 0.1"]),
        ({"config": {"feedback.per_round": 0}}, ["body", "config", "feedback.per_round"],
         ["must be positive"]),
        ({"config": {"feedback.labels_per_query": 0}},
         ["body", "config", "feedback.labels_per_query"], ["between 1 and 10, got 0"]),
        ({"config": {"feedback.labels_per_query": 11}},
         ["body", "config", "feedback.labels_per_query"], ["between 1 and 10, got 11"]),
        ({"config": {"feedback.gold_rate": 0.6}}, ["body", "config", "feedback.gold_rate"],
         ["between 0.0 and 0.5, got 0.6"]),
        ({"config": {"feedback.gold_rate": -0.1}}, ["body", "config", "feedback.gold_rate"],
         ["between 0.0 and 0.5"]),
        # Absurd sizes: refused with the limit named, not trained "forever".
        ({"config": {"steps": 1e30}}, ["body", "config", "steps"],
         ["at most 2147483647", "1e+30"]),
        ({"config": {"steps": 2147483648}}, ["body", "config", "steps"],
         ["at most 2147483647", "2147483648"]),
        ({"config": {"replay_capacity": 10**12}}, ["body", "config", "replay_capacity"],
         ["at most 2147483647"]),
    ],
)
def test_a_run_no_worker_could_train_is_422_naming_the_field_and_what_is_valid(
    client: TestClient, session: Session, override: dict[str, Any], loc: list[str],
    words: list[str]
) -> None:
    """Checked as the worker will build it, before it is stored: never a 201 for a run that
    would fail later, and never a config value silently overwritten."""
    before = snapshot(session)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 0} | override
    response = client.post("/api/runs", json=body, headers=OPERATOR)
    assert response.status_code == 422, response.text
    [error] = response.json()["detail"]
    assert error["loc"] == loc
    for word in words:
        assert word in error["msg"]
    assert snapshot(session) == before


def test_a_teacher_switch_with_bad_parameters_is_422_and_changes_nothing(
    client: TestClient, session: Session
) -> None:
    run_id = client.post("/api/runs", json={"task": "dmc:cheetah_run", "algo": "pebble",
                                           "budget": 10}, headers=OPERATOR).json()["id"]
    before = snapshot(session)
    for params, loc in [({"eps": 1.5}, ["body", "params", "eps"]),
                        ({"epss": 0.1}, ["body", "params", "epss"])]:
        response = client.put(f"/api/runs/{run_id}/teacher",
                              json={"teacher": "scripted", "params": params}, headers=OPERATOR)
        assert response.status_code == 422, response.text
        assert response.json()["detail"][0]["loc"] == loc
    assert snapshot(session) == before


def test_a_body_that_is_not_json_is_422(client: TestClient) -> None:
    response = client.post(
        "/api/runs", content=b"{not json", headers=OPERATOR | {"Content-Type": "application/json"}
    )
    assert response.status_code == 422 and response.headers["content-type"] == "application/json"


def test_auth_is_401_without_a_valid_token_and_403_for_the_wrong_role(
    client: TestClient, session: Session
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    before = snapshot(session)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 0}

    missing = client.post("/api/runs", json=body)
    assert missing.status_code == 401 and "missing bearer token" in missing.json()["detail"]
    assert missing.headers["www-authenticate"] == "Bearer"
    for wrong in ["nonsense", "1.not-the-secret", "99.x", OPERATOR["Authorization"][7:] + "x"]:
        response = client.post("/api/runs", json=body, headers=bearer(wrong))
        assert response.status_code == 401 and "invalid" in response.json()["detail"]
    basic = client.get("/api/runs", headers={"Authorization": "Basic YWxpY2U6eA=="})
    assert basic.status_code == 401

    forbidden = client.post("/api/runs", json=body, headers=alice)
    assert (
        forbidden.status_code == 403 and "'alice' is not an operator" in forbidden.json()["detail"]
    )
    assert client.post("/api/labellers", json={"name": "eve"}, headers=alice).status_code == 403
    # The settings' operator token manages, but is nobody who could answer a query.
    not_a_labeller = client.get("/api/label/next", headers=OPERATOR)
    assert not_a_labeller.status_code == 403 and "not a labeller" in not_a_labeller.json()["detail"]
    assert snapshot(session) == before


def test_labellers_are_created_with_a_token_shown_once(
    client: TestClient, session: Session
) -> None:
    created = client.post(
        "/api/labellers", json={"name": "olga", "role": "operator"}, headers=OPERATOR
    ).json()
    assert set(created) == {"id", "name", "role", "token"} and created["role"] == "operator"
    # The new operator's own token works for operator endpoints.
    assert client.get("/api/runs", headers=bearer(created["token"])).status_code == 200

    listed = client.get("/api/labellers", headers=OPERATOR)
    assert [row["name"] for row in listed.json()] == ["olga"]
    assert created["token"] not in listed.text and "hash" not in listed.text

    before = snapshot(session)
    duplicate = client.post("/api/labellers", json={"name": "olga"}, headers=OPERATOR)
    assert duplicate.status_code == 409 and "olga" in duplicate.json()["detail"]
    bad_role = client.post("/api/labellers", json={"name": "x", "role": "admin"}, headers=OPERATOR)
    assert bad_role.status_code == 422
    assert snapshot(session) == before


def test_an_operator_revokes_restores_renames_and_promotes_a_labeller(
    client: TestClient, session: Session
) -> None:
    token = new_labeller(client, "mallory")
    mallory = bearer(token)
    labeller_id = int(token.split(".")[0])
    assert client.get("/api/label/count", headers=mallory).status_code == 200  # now cached

    revoked = client.patch(f"/api/labellers/{labeller_id}", json={"active": False},
                           headers=OPERATOR)
    assert revoked.status_code == 200 and revoked.json()["active"] is False
    # At once in this process, although the token was in the auth cache a moment ago.
    refused = client.get("/api/label/count", headers=mallory)
    assert refused.status_code == 401 and "revoked" in refused.json()["detail"]
    listed = client.get("/api/labellers", headers=OPERATOR).json()
    assert [(row["name"], row["active"]) for row in listed] == [("mallory", False)]

    restored = client.patch(
        f"/api/labellers/{labeller_id}",
        json={"active": True, "name": "marta", "role": "operator"},
        headers=OPERATOR,
    ).json()
    assert (restored["name"], restored["role"], restored["active"]) == ("marta", "operator", True)
    assert client.get("/api/runs", headers=mallory).status_code == 200  # an operator now

    new_labeller(client, "bob")
    before = snapshot(session)
    for body, status, words in [
        ({"name": "bob"}, 409, "bob"),
        ({"role": "admin"}, 422, "role"),
        ({"active": "maybe"}, 422, "active"),
        ({"name": ""}, 422, "name"),
        ({"token_hash": "x"}, 422, "token_hash"),
    ]:
        response = client.patch(f"/api/labellers/{labeller_id}", json=body, headers=OPERATOR)
        assert response.status_code == status and words in response.text, response.text
    missing = client.patch("/api/labellers/999", json={"active": False}, headers=OPERATOR)
    assert missing.status_code == 404 and "999" in missing.json()["detail"]
    lena = bearer(new_labeller(client, "lena"))
    not_operator = client.patch(f"/api/labellers/{labeller_id}", json={"active": False},
                                headers=lena)
    assert not_operator.status_code == 403
    after = snapshot(session)
    assert after["labellers"][:2] == before["labellers"]  # only lena was added


def test_a_new_token_for_a_labeller_invalidates_the_old_one(client: TestClient) -> None:
    old = new_labeller(client, "alice")
    labeller_id = int(old.split(".")[0])
    assert client.get("/api/label/count", headers=bearer(old)).status_code == 200  # cached
    rotated = client.post(f"/api/labellers/{labeller_id}/token", headers=OPERATOR)
    assert rotated.status_code == 200
    new = rotated.json()["token"]
    assert rotated.json()["name"] == "alice" and new != old
    assert client.get("/api/label/count", headers=bearer(old)).status_code == 401
    assert client.get("/api/label/count", headers=bearer(new)).status_code == 200
    assert client.post("/api/labellers/999/token", headers=OPERATOR).status_code == 404


def test_settings_come_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SEPOA_DATABASE_URL", raising=False)
    monkeypatch.delenv("SEPOA_DATABASE_URL_FILE", raising=False)
    monkeypatch.setenv("SEPOA_DATA_DIR", "/srv/sepoa")
    monkeypatch.setenv("SEPOA_LEASE_SECONDS", "30")
    get_settings.cache_clear()
    try:
        settings = get_settings()
        assert get_settings() is settings
        assert str(settings.clips_dir) == "/srv/sepoa/clips" and settings.lease_seconds == 30
        assert settings.database_url == "sqlite:////srv/sepoa/queue.db"
    finally:
        get_settings.cache_clear()


def assert_served_alone_into(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A server made from the environment, as uvicorn makes it, stores a labeller it is asked
    to create in the SQLite queue in `folder`."""
    monkeypatch.setenv("SEPOA_OPERATOR_TOKEN", OPERATOR_TOKEN)
    get_settings.cache_clear()
    try:
        with TestClient(create_app()) as client:
            new_labeller(client, "ann")
    finally:
        get_settings.cache_clear()
    engine = make_engine(sqlite_url(folder))
    try:
        with session_factory(engine)() as session:
            assert find_labeller(session, name="ann") is not None
    finally:
        engine.dispose()


def test_a_server_started_alone_keeps_its_queue_in_the_data_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`uvicorn server.app:app` with SEPOA_DATA_DIR alone opens `<data dir>/queue.db`, as
    `sepoa up` does (it opened data/queue.db under the working folder); a URL given still
    wins, and so does a URL file."""
    monkeypatch.chdir(tmp_path)  # where data/queue.db would be made
    data = tmp_path / "study"
    monkeypatch.delenv("SEPOA_DATABASE_URL", raising=False)
    monkeypatch.delenv("SEPOA_DATABASE_URL_FILE", raising=False)
    monkeypatch.setenv("SEPOA_DATA_DIR", str(data))
    assert_served_alone_into(data, monkeypatch)
    assert not (tmp_path / "data").exists()
    given = sqlite_url(tmp_path / "elsewhere")
    assert Settings(data_dir=data, database_url=given).database_url == given
    url_file = tmp_path / "queue-url"
    url_file.write_text(f"{given}\n")
    url_file.chmod(0o600)
    assert Settings(data_dir=data, database_url_file=str(url_file)).database_url == given


def test_a_server_started_alone_opens_the_database_the_url_file_names(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`uvicorn server.app:app` reads SEPOA_DATABASE_URL_FILE as every `sepoa` command does
    (it opened data/queue.db instead); a file it cannot use ends the start in one line."""
    monkeypatch.chdir(tmp_path)  # where data/queue.db would be made
    url_file = tmp_path / "queue-url"
    url_file.write_text(f"# the study's database\n{sqlite_url(tmp_path)}\n")
    url_file.chmod(0o600)
    monkeypatch.delenv("SEPOA_DATABASE_URL", raising=False)
    monkeypatch.setenv("SEPOA_DATABASE_URL_FILE", str(url_file))
    assert_served_alone_into(tmp_path, monkeypatch)
    assert not (tmp_path / "data" / "queue.db").exists()
    empty, missing = tmp_path / "empty", tmp_path / "missing"
    empty.write_text("# nothing yet\n")
    empty.chmod(0o600)
    url_file.chmod(0o644)  # readable by others: refused, as libpq refuses such a file
    try:
        for path, words in ((url_file, "chmod 600"), (empty, "holds no URL"),
                            (missing, "No such file")):
            monkeypatch.setenv("SEPOA_DATABASE_URL_FILE", str(path))
            get_settings.cache_clear()
            with pytest.raises(SystemExit) as ended:
                create_app()
            assert str(ended.value).startswith(f"error: database URL file {path}")
            assert words in str(ended.value) and "\n" not in str(ended.value)
    finally:
        get_settings.cache_clear()


def test_a_server_started_alone_refuses_a_queue_in_memory_in_one_line(
    monkeypatch: pytest.MonkeyPatch
) -> None:
    """SEPOA_DATABASE_URL=sqlite:// gave the server a queue of its own in memory, which its
    workers never saw (and the first request found no tables); it now ends the start."""
    monkeypatch.delenv("SEPOA_DATABASE_URL_FILE", raising=False)
    try:
        for url in ("sqlite://", "sqlite:///:memory:"):
            monkeypatch.setenv("SEPOA_DATABASE_URL", url)
            get_settings.cache_clear()
            with pytest.raises(SystemExit) as ended:
                create_app()
            said = str(ended.value)
            assert said.startswith("error: ") and "in memory" in said and "\n" not in said
            assert "sqlite:///PATH or postgresql+psycopg://" in said
    finally:
        get_settings.cache_clear()


def test_the_label_api_works_on_one_thread_on_sqlite_and_on_the_pool_on_postgres() -> None:
    """SQLite's writes run one at a time, so more threads would only pass its lock around."""
    assert Settings(database_url="sqlite:///q.db", threadpool_size=6).label_thread_count == 1
    postgres = Settings(database_url="postgresql+psycopg://u@h/db", threadpool_size=6)
    assert postgres.label_thread_count == 6
    assert Settings(database_url="sqlite:///q.db", label_threads=3).label_thread_count == 3


def test_a_live_runs_answers_per_query_and_gold_rate_cannot_be_changed(
    client: TestClient, session: Session
) -> None:
    """They are fixed when the run is created: counts of answers and of gold answers stay true
    to the run's one setting."""
    run = new_run(client, algo="pebble", config={"feedback.labels_per_query": 3})
    before = snapshot(session)
    for method in ("PATCH", "PUT"):
        response = client.request(method, f"/api/runs/{run['id']}", headers=OPERATOR,
                                   json={"config": {"feedback.labels_per_query": 1}})
        assert response.status_code == 405, response.text
        assert "GET" in response.headers["allow"]
    switched = client.put(f"/api/runs/{run['id']}/teacher", headers=OPERATOR,
                          json={"teacher": "human", "teacher_params": {"labels_per_query": 1}})
    assert switched.status_code == 422 and "labels_per_query" in switched.text
    assert snapshot(session) == before

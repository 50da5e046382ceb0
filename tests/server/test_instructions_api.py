"""A run's instruction to labellers: the task's own by default, the operator's at creation or
later; the label page reads it per run; the export gives each label the text it was answered
under; bad input is a 4xx that names the field."""

from __future__ import annotations

import json
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run, running_run_with_queries
from sqlalchemy.orm import Session

from labelqueue import EXPORT_SCHEMA_VERSION
from runvocab.instructions import default_instruction, instruction_sha256
from server.settings import Settings


def answer(client: TestClient, token: str, run_id: int) -> None:
    nxt = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    body = {"choice": "left", "left_is_first": nxt["left_is_first"],
            "shown_at": "2026-01-01T00:00:00Z"}
    response = client.post(f"/api/label/{nxt['query_id']}", json=body, headers=bearer(token))
    assert response.status_code == 201, response.text


def export(client: TestClient, run_id: int) -> list[dict[str, Any]]:
    response = client.get(f"/api/export?format=jsonl&run_id={run_id}", headers=OPERATOR)
    assert response.status_code == 200, response.text
    return [json.loads(line) for line in response.text.splitlines()]


def test_a_run_shows_its_tasks_instruction_unless_the_operator_gives_one(
    client: TestClient,
) -> None:
    token = new_labeller(client, "alice")
    plain = new_run(client)
    assert plain["instruction"] is None
    assert plain["instruction_text"] == default_instruction("dmc:cheetah_run")
    assert "forward" in plain["instruction_text"] and "fast" in plain["instruction_text"]
    assert plain["clip_size"] is None

    own = new_run(client, instruction="  Prefer the cheetah that stays upright.\r\n",
                  clip_size="320x240")
    assert own["instruction"] == own["instruction_text"] == "Prefer the cheetah that stays upright."
    assert own["clip_size"] == "320x240"

    brief = client.get(f"/api/label/runs/{own['id']}", headers=bearer(token)).json()
    assert brief["instruction"] == "Prefer the cheetah that stays upright."
    assert brief["instruction_sha256"] == instruction_sha256(brief["instruction"])
    assert (brief["clip_width"], brief["clip_height"]) == (320, 240)
    # cheetah: 0.01 s per step; 50 steps play in 1.5 s, so a clip runs at a third of real time
    assert brief["step_seconds"] == 0.01
    assert abs(brief["real_time_ratio"] - 1 / 3) < 1e-9
    default = client.get(f"/api/label/runs/{plain['id']}", headers=bearer(token)).json()
    assert (default["clip_width"], default["clip_height"]) == (256, 256)


def test_an_edited_instruction_is_shown_from_then_on_and_the_export_keeps_what_each_label_saw(
    client: TestClient, session: Session, settings: Settings
) -> None:
    token = new_labeller(client, "alice")
    run_id, _ = running_run_with_queries(client, session, settings, n=3)
    answer(client, token, run_id)

    edited = client.put(f"/api/runs/{run_id}/instruction",
                        json={"instruction": "Faster is better; nothing else counts."},
                        headers=OPERATOR)
    assert edited.status_code == 200, edited.text
    assert edited.json()["instruction_text"] == "Faster is better; nothing else counts."
    brief = client.get(f"/api/label/runs/{run_id}", headers=bearer(token)).json()
    assert brief["instruction"] == "Faster is better; nothing else counts."
    answer(client, token, run_id)

    back = client.put(f"/api/runs/{run_id}/instruction", json={"instruction": None},
                      headers=OPERATOR)
    assert back.json()["instruction"] is None
    answer(client, token, run_id)

    rows = export(client, run_id)
    texts = [row["instruction"] for row in rows]
    default = default_instruction("dmc:cheetah_run")
    assert texts == [default, "Faster is better; nothing else counts.", default]
    assert [row["instruction_sha256"] for row in rows] == [instruction_sha256(t) for t in texts]
    assert {row["schema_version"] for row in rows} == {EXPORT_SCHEMA_VERSION}


def test_bad_instructions_and_clip_sizes_are_a_422_naming_the_field(client: TestClient) -> None:
    token = new_labeller(client, "alice")
    run = new_run(client)
    body = {"task": "dmc:cheetah_run", "algo": "sac", "budget": 1}
    cases = [
        ("POST", "/api/runs", body | {"instruction": "   "}, "instruction", "empty"),
        ("POST", "/api/runs", body | {"instruction": "x" * 2001}, "instruction", "2000"),
        ("POST", "/api/runs", body | {"instruction": "a\x00b"}, "instruction", "control"),
        ("POST", "/api/runs", body | {"instruction": 5}, "instruction", "string"),
        ("POST", "/api/runs", body | {"clip_size": "1920x1080"}, "clip_size", "256x256"),
        ("POST", "/api/runs", body | {"clip_size": "256X256"}, "clip_size", "did you mean"),
        ("PUT", f"/api/runs/{run['id']}/instruction", {"instruction": ""}, "instruction",
         "empty"),
        ("PUT", f"/api/runs/{run['id']}/instruction", {}, "instruction", "required"),
        ("PUT", f"/api/runs/{run['id']}/instruction", {"instruction": "ok", "x": 1}, "x",
         "extra"),
    ]
    for method, url, payload, field, words in cases:
        response = client.request(method, url, json=payload, headers=OPERATOR)
        assert response.status_code == 422, (url, payload, response.text)
        detail = response.json()["detail"]
        assert any(field in error["loc"] for error in detail), (payload, detail)
        assert words.lower() in response.text.lower(), (payload, detail)

    assert client.put("/api/runs/999/instruction", json={"instruction": "x"},
                      headers=OPERATOR).status_code == 404
    assert client.get("/api/label/runs/999", headers=bearer(token)).status_code == 404
    assert client.get("/api/label/runs/0", headers=bearer(token)).status_code == 422
    # The operator's edit is for operators; the brief is for labellers.
    assert client.put(f"/api/runs/{run['id']}/instruction", json={"instruction": "x"},
                      headers=bearer(token)).status_code == 403
    assert client.get(f"/api/label/runs/{run['id']}", headers=OPERATOR).status_code == 403
    assert client.get(f"/api/label/runs/{run['id']}").status_code == 401


def test_a_one_run_participant_reads_their_runs_instruction_only(client: TestClient) -> None:
    mine, other = (new_run(client, instruction=f"Secret words of run {i}.")["id"]
                   for i in (1, 2))
    study = client.post("/api/invites", json={"run_id": mine}, headers=OPERATOR).json()
    token = client.post(f"/api/join/{study['code']}", json={"participant": "p1"}).json()["token"]
    assert client.get(f"/api/label/runs/{mine}", headers=bearer(token)).json()[
        "instruction"] == "Secret words of run 1."
    # Another run's instruction is refused as its pairs are, in the same words.
    refused = client.get(f"/api/label/runs/{other}", headers=bearer(token))
    pairs = client.get(f"/api/label/next?run_id={other}", headers=bearer(token))
    assert refused.status_code == pairs.status_code == 403
    assert refused.json() == pairs.json()
    assert "Secret" not in refused.text and f"for run {mine}" in refused.text
    # Joined by an all-runs invite, or by none: every run's.
    everyone = client.post("/api/invites", json={}, headers=OPERATOR).json()
    for who in (client.post(f"/api/join/{everyone['code']}", json={}).json()["token"],
                new_labeller(client, "alice")):
        assert client.get(f"/api/label/runs/{other}", headers=bearer(who)).status_code == 200

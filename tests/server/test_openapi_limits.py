"""The OpenAPI document states the limits the server enforces: a request valid by the document
is not refused for a limit it does not state, and one the document refuses the server refuses
too (instruction text, calibration bins, after_step, shown_at, an invite's expiry and redirect
URL, a run's config and teacher parameters)."""

from __future__ import annotations

import json
import re
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run, running_run_with_queries
from sqlalchemy.orm import Session

from runvocab.instructions import MAX_CHARS
from runvocab.names import ALGOS
from server.settings import Settings


def _schema(document: dict[str, Any], schema: dict[str, Any]) -> dict[str, Any]:
    """The value's branch of a nullable schema (`anyOf: [..., null]`), with the keywords
    stated beside the `anyOf` (JSON Schema applies them to values of their type only)."""
    value = next((s for s in schema.get("anyOf", [schema]) if s.get("type") != "null"), {})
    return {k: v for k, v in schema.items() if k != "anyOf"} | value


def _valid(schema: dict[str, Any], value: str) -> bool:
    return (schema.get("minLength", 0) <= len(value) <= schema.get("maxLength", 10**9)
            and re.search(schema.get("pattern", ""), value) is not None)


def test_the_instruction_limits_are_in_the_document(client: TestClient) -> None:
    document = client.get("/openapi.json").json()
    run_id = new_run(client)["id"]
    for body in ("RunCreate", "InstructionUpdate"):
        schema = _schema(document, document["components"]["schemas"][body]["properties"]
                         ["instruction"])
        assert schema["maxLength"] == MAX_CHARS and schema["minLength"] == 1
        for text in ["Run fast.", "Faster\nis better\tstill.", "x" * MAX_CHARS, "é" * 50,
                     "", "   ", "\n\t", "x" * (MAX_CHARS + 1), "a\x00b", "a\x1bb", "\u3000"]:
            response = client.put(f"/api/runs/{run_id}/instruction", json={"instruction": text},
                                  headers=OPERATOR)
            assert (response.status_code == 200) == _valid(schema, text), (body, text[:20],
                                                                            response.text)


def test_the_bins_and_after_step_limits_are_in_the_document(client: TestClient) -> None:
    document = client.get("/openapi.json").json()
    [bins] = [p for p in document["paths"]["/api/quality/calibration"]["get"]["parameters"]
              if p["name"] == "bins"]
    schema = _schema(document, bins["schema"])
    for text in ["0,0.1,0.2,0.5,1,inf", "0, 1e-3 ,inf", ".0,2", "0,1", ",".join(
            ["0"] + [str(i) for i in range(1, 101)]), "0", "0,", "0.2,0.5", "0,x", "0,nan",
            "0,-1", ",".join(["0"] + [str(i) for i in range(1, 102)])]:
        response = client.get("/api/quality/calibration", params={"bins": text},
                              headers=OPERATOR)
        assert (response.status_code == 200) == _valid(schema, text), (text[:30], response.text)
    # Valid by the document but for the order of the edges, which it states in words only.
    assert "each larger than the one before" in bins["description"]

    run_id = new_run(client)["id"]
    [after] = [p for p in document["paths"]["/api/runs/{run_id}/metrics"]["get"]["parameters"]
               if p["name"] == "after_step"]
    assert _schema(document, after["schema"])["minimum"] == 0
    path = f"/api/runs/{run_id}/metrics"
    assert client.get(path, params={"after_step": 0}, headers=OPERATOR).status_code == 200
    assert client.get(path, params={"after_step": -1}, headers=OPERATOR).status_code == 422


def test_what_the_document_refuses_the_server_refuses_and_what_it_takes_the_server_takes(
    client: TestClient, session: Session, settings: Settings
) -> None:
    document = client.get("/openapi.json").json()
    schemas = document["components"]["schemas"]
    alice = bearer(new_labeller(client, "alice"))
    running_run_with_queries(client, session, settings, n=2)
    shown = client.get("/api/label/next", headers=alice).json()
    # shown_at is a date-time as text, with its offset: a number, or a time with no zone, is
    # none (it was read as seconds since 1970, or as UTC).
    assert schemas["LabelSubmit"]["properties"]["shown_at"]["format"] == "date-time"
    for when in (0, "0", 1700000000, "2026-01-01T12:00:00"):
        refused = client.post(f"/api/label/{shown['query_id']}",
                              json={"choice": "left", "shown_at": when}, headers=alice)
        assert refused.status_code == 422, (when, refused.text)
        [problem] = refused.json()["detail"]
        assert problem["loc"] == ["body", "shown_at"] and "RFC 3339" in problem["msg"]
    # A flag goes with a skip, and a note with a flag: the document says so too.
    assert len(schemas["LabelSubmit"]["allOf"]) == 2

    # Expiry: from a minute; a redirect URL whose host Python cannot read is refused by both,
    # naming the field.
    invite = schemas["InviteCreate"]["properties"]
    assert invite["expires_in_days"]["minimum"] == 1 / 1440
    for body in ({"expires_in_days": 1e-12}, {"redirect_url": "https://[2a]/done"}):
        refused = client.post("/api/invites", json=body, headers=OPERATOR)
        assert refused.status_code == 422 and next(iter(body)) in refused.text, refused.text
    assert not re.search(_schema(document, invite["redirect_url"])["pattern"],
                         "https://[2a]/done")
    made = client.post("/api/invites", json={"expires_in_days": 1 / 1440,
                                             "redirect_url": "https://e.org/x?cc={code}"},
                       headers=OPERATOR)
    assert made.status_code == 201, made.text
    # Names, notes and consent texts: something besides white space (and no NUL).
    consent = _schema(document, invite["consent_text"])
    for text in ("We keep your answers.", " x ", "", " ", "\t\n", "\u3000", "\x01", "a\x00b"):
        response = client.post("/api/invites", json={"consent_text": text}, headers=OPERATOR)
        assert (response.status_code == 201) == _valid(consent, text), (text, response.text)

    # A run's config and teacher parameters: their field names and the JSON each takes.
    config = _schema(document, schemas["RunCreate"]["properties"]["config"])
    assert "sac.lr" in config["propertyNames"]["enum"]
    assert "run_dir" not in config["propertyNames"]["enum"]  # the worker's, never a run's
    assert config["properties"]["algo"]["enum"] == list(ALGOS)
    teacher = _schema(document, schemas["TeacherUpdate"]["properties"]["params"])
    assert set(teacher["propertyNames"]["enum"]) >= {"eps", "beta", "tie"}
    run = new_run(client, config={"sac.lr": "0.001", "reward.surf": "yes"},
                  teacher_params={"eps": 0.1})
    assert run["config"]["sac.lr"] == "0.001"
    # The defaults' config is a JSON object of the same fields, as the document states it.
    [param] = [p for p in document["paths"]["/api/runs/defaults"]["get"]["parameters"]
               if p["name"] == "config"]
    assert "sac.lr" in param["content"]["application/json"]["schema"]["propertyNames"]["enum"]
    defaults = client.get("/api/runs/defaults", params={
        "task": "dmc:cheetah_run", "config": json.dumps({"feedback.budget": 77})},
        headers=OPERATOR)
    assert defaults.status_code == 200 and defaults.json()["budget"] == 77
    for text in ("", "[1]", "{", "x" * (17 * 1024)):
        refused = client.get("/api/runs/defaults",
                             params={"task": "dmc:cheetah_run", "config": text},
                             headers=OPERATOR)
        assert refused.status_code == 422
        assert refused.json()["detail"][0]["loc"] == ["query", "config"]


def test_an_external_runs_teacher_is_a_conflict_not_a_bad_preset(client: TestClient) -> None:
    run = client.post("/api/runs/external", json={"task": "my-task", "budget": 10},
                      headers=OPERATOR)
    assert run.status_code == 201, run.text
    refused = client.put(f"/api/runs/{run.json()['id']}/teacher",
                         json={"teacher": "scripted", "params": {"eps": 0.1}}, headers=OPERATOR)
    assert refused.status_code == 409 and "external run" in refused.json()["detail"]

"""The OpenAPI document states the limits the server enforces: a request valid by the document
is not refused for a limit it does not state, and one the document refuses the server refuses
too (instruction text, calibration bins, after_step)."""

from __future__ import annotations

import re
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, new_run

from runvocab.instructions import MAX_CHARS


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

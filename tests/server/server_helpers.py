"""Builders shared by the server tests (fixtures are in conftest.py)."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient
from hidden_truth import SECRET_RETURNS
from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import (
    Label,
    Labeller,
    Metric,
    Query,
    Run,
    claim_run,
    push_queries,
    set_clips,
)
from server.settings import Settings

OPERATOR_TOKEN = "test-operator-token-0123456789"


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


OPERATOR = bearer(OPERATOR_TOKEN)


def new_labeller(client: TestClient, name: str, role: str = "labeller") -> str:
    """A labeller created over REST; its bearer token."""
    response = client.post("/api/labellers", json={"name": name, "role": role}, headers=OPERATOR)
    assert response.status_code == 201, response.text
    token: str = response.json()["token"]
    return token


def new_run(client: TestClient, **overrides: Any) -> dict[str, Any]:
    body = {"task": "dmc:cheetah_run", "algo": "sepoa", "budget": 10, "preset": "tiny"}
    response = client.post("/api/runs", json=body | overrides, headers=OPERATOR)
    assert response.status_code == 201, response.text
    run: dict[str, Any] = response.json()
    return run


def query_spec(position: int) -> dict[str, Any]:
    return {
        "round": 0,
        "position": position,
        "segment_length": 50,
        "first_trajectory": 2 * position,
        "first_start": 10,
        "second_trajectory": 2 * position + 1,
        "second_start": 20,
        **SECRET_RETURNS,
    }


def running_run_with_queries(
    client: TestClient, session: Session, settings: Settings, n: int = 2, **run: Any
) -> tuple[int, list[int]]:
    """A human-taught run claimed by a worker, with `n` rendered queries; (run id, query ids)."""
    run_id = new_run(client, **run)["id"]
    claimed = claim_run(session, worker_id="worker-1")
    assert claimed is not None and claimed.id == run_id
    ids = push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(n)])
    for query_id in ids:
        keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            path = settings.clips_root / key
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(f"fake mp4 {key} ".encode() * 20)
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    return run_id, ids


def snapshot(session: Session) -> dict[str, list[tuple[Any, ...]]]:
    """Every stored row of every table, to check that a refused request changed nothing."""
    tables: dict[str, list[tuple[Any, ...]]] = {}
    for model in (Labeller, Run, Query, Label, Metric):
        rows = session.execute(select(model.__table__))
        tables[model.__tablename__] = [tuple(row) for row in rows]
    session.commit()
    return tables

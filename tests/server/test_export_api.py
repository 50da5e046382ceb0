"""The operator's export download: every format with its headers, one run's labels, refusals."""

from __future__ import annotations

import csv
import io
import json
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient
from server_helpers import (
    OPERATOR,
    SECRET_RETURNS,
    bearer,
    new_labeller,
    new_run,
    query_spec,
    running_run_with_queries,
    snapshot,
)
from sqlalchemy.orm import Session

from labelqueue import (
    EXPORT_COLUMNS,
    EXPORT_SCHEMA_VERSION,
    claim_run,
    export_rows,
    push_queries,
    set_clips,
)
from rundata.label_files import PARQUET_VERSION_KEY, write_export
from server.settings import Settings

NAMES = [column.name for column in EXPORT_COLUMNS]
MEDIA = {
    "jsonl": "application/x-ndjson",
    "csv": "text/csv; charset=utf-8",
    "parquet": "application/vnd.apache.parquet",
}


def answer(client: TestClient, token: str, choice: str) -> int:
    """The labeller answers its next query as the page would; the query's id."""
    shown = client.get("/api/label/next", headers=bearer(token)).json()
    body = {
        "choice": choice,
        "left_is_first": shown["left_is_first"],
        "shown_at": datetime.now(UTC).isoformat(),
    }
    response = client.post(f"/api/label/{shown['query_id']}", json=body, headers=bearer(token))
    assert response.status_code == 201, response.text
    query_id: int = shown["query_id"]
    return query_id


def second_run(client: TestClient, session: Session, settings: Settings) -> int:
    """Another human-taught run, claimed by a second worker, with two rendered queries."""
    run_id = new_run(client, name="second")["id"]
    claimed = claim_run(session, worker_id="worker-2")
    assert claimed is not None and claimed.id == run_id
    for query_id in push_queries(session, run_id=run_id, queries=[query_spec(0), query_spec(1)]):
        keys = [f"run{run_id}/q{query_id}-{side}.mp4" for side in ("a", "b")]
        for key in keys:
            (settings.clips_root / key).parent.mkdir(parents=True, exist_ok=True)
            (settings.clips_root / key).write_bytes(b"fake mp4")
        set_clips(session, query_id=query_id, first_clip=keys[0], second_clip=keys[1])
    return run_id


def two_runs_with_labels(
    client: TestClient, session: Session, settings: Settings
) -> tuple[int, int]:
    """Run "first": alice answers left; run "second": bob cant_tell, then alice equal."""
    first, _ = running_run_with_queries(client, session, settings, n=1, name="first")
    alice, bob = new_labeller(client, "alice"), new_labeller(client, "bob")
    answer(client, alice, "left")
    second = second_run(client, session, settings)
    answer(client, bob, "cant_tell")
    answer(client, alice, "equal")
    return first, second


def library_bytes(session: Session, fmt: str, run_id: int | None = None) -> bytes:
    out = io.BytesIO()
    write_export(session, fmt=fmt, out=out, run_id=run_id)
    return out.getvalue()


@pytest.mark.parametrize("fmt", ["jsonl", "csv", "parquet"])
def test_an_operator_downloads_every_label_in_each_format(
    client: TestClient, session: Session, settings: Settings, fmt: str
) -> None:
    two_runs_with_labels(client, session, settings)
    response = client.get(f"/api/export?format={fmt}", headers=OPERATOR)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == MEDIA[fmt]
    assert response.headers["content-disposition"] == (
        f'attachment; filename="labels-v{EXPORT_SCHEMA_VERSION}.{fmt}"'
    )
    assert int(response.headers["content-length"]) == len(response.content)
    expected = list(export_rows(session))
    assert [row["labeller_name"] for row in expected] == ["alice", "bob", "alice"]
    assert [row["run_name"] for row in expected] == ["first", "second", "second"]
    assert [row["answer"] for row in expected][1:] == ["cant_tell", "equal"]

    if fmt == "jsonl":
        lines = [json.loads(line) for line in response.text.splitlines()]
        assert [line["label_id"] for line in lines] == [row["label_id"] for row in expected]
        assert [list(line) for line in lines] == [NAMES] * 3
        # Ground truth is in the operator's export.
        assert lines[0]["first_segment_return"] == SECRET_RETURNS["first_segment_return"]
        assert response.content == library_bytes(session, fmt)
    elif fmt == "csv":
        rows = list(csv.DictReader(io.StringIO(response.text)))
        assert list(rows[0]) == NAMES
        assert [row["choice"] for row in rows][1:] == ["cant_tell", "equal"]
        assert rows[1]["answer"] == "cant_tell" and rows[1]["correct"] == ""
        assert response.content == library_bytes(session, fmt)
    else:
        table = pq.read_table(io.BytesIO(response.content))
        assert table.schema.metadata[PARQUET_VERSION_KEY.encode()] == b"3"
        assert table.column_names == NAMES
        assert table.column("label_id").to_pylist() == [row["label_id"] for row in expected]
        assert table.column("answered_at").to_pylist() == [row["answered_at"] for row in expected]
        assert table.to_pylist() == expected


def test_the_format_defaults_to_jsonl_and_a_run_filter_names_the_file(
    client: TestClient, session: Session, settings: Settings
) -> None:
    first, second = two_runs_with_labels(client, session, settings)
    response = client.get("/api/export", headers=OPERATOR)
    assert response.headers["content-type"] == MEDIA["jsonl"]
    assert len(response.text.splitlines()) == 3

    response = client.get(f"/api/export?format=csv&run_id={second}", headers=OPERATOR)
    assert response.status_code == 200, response.text
    assert response.headers["content-disposition"] == (
        f'attachment; filename="labels-run{second}-v{EXPORT_SCHEMA_VERSION}.csv"'
    )
    rows = list(csv.DictReader(io.StringIO(response.text)))
    assert [(row["run_id"], row["run_name"], row["choice"]) for row in rows] == [
        (str(second), "second", "cant_tell"),
        (str(second), "second", "equal"),
    ]
    assert response.content == library_bytes(session, "csv", second)

    response = client.get(f"/api/export?format=jsonl&run_id={first}", headers=OPERATOR)
    lines = [json.loads(line) for line in response.text.splitlines()]
    assert [(line["run_name"], line["labeller_name"]) for line in lines] == [("first", "alice")]


def test_a_run_without_labels_is_an_empty_file_with_its_columns(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, _ = running_run_with_queries(client, session, settings, n=1)
    assert client.get(f"/api/export?run_id={run_id}", headers=OPERATOR).content == b""
    response = client.get(f"/api/export?format=csv&run_id={run_id}", headers=OPERATOR)
    assert response.text == ",".join(NAMES) + "\n"
    response = client.get(f"/api/export?format=parquet&run_id={run_id}", headers=OPERATOR)
    table = pq.read_table(io.BytesIO(response.content))
    assert table.num_rows == 0 and table.column_names == NAMES


def test_unknown_runs_and_bad_formats_are_refused_and_change_nothing(
    client: TestClient, session: Session, settings: Settings
) -> None:
    two_runs_with_labels(client, session, settings)
    before = snapshot(session)
    response = client.get("/api/export?format=csv&run_id=999", headers=OPERATOR)
    assert response.status_code == 404 and "run 999" in response.json()["detail"]
    assert "content-disposition" not in response.headers
    for query in ("format=xlsx", "format=CSV", "run_id=abc", "format="):
        response = client.get(f"/api/export?{query}", headers=OPERATOR)
        assert response.status_code == 422, query
    detail = client.get("/api/export?format=xlsx", headers=OPERATOR).json()["detail"]
    assert detail[0]["loc"] == ["query", "format"]
    assert snapshot(session) == before


def test_only_operators_may_export(
    client: TestClient, session: Session, settings: Settings
) -> None:
    two_runs_with_labels(client, session, settings)
    boss = new_labeller(client, "boss", role="operator")
    carol = new_labeller(client, "carol")
    before = snapshot(session)
    assert client.get("/api/export").status_code == 401
    assert client.get("/api/export", headers=bearer("1.not-a-token")).status_code == 401
    # Refused before the format is even looked at.
    assert client.get("/api/export?format=xlsx").status_code == 401
    refused = client.get("/api/export?format=csv", headers=bearer(carol))
    assert refused.status_code == 403
    assert str(SECRET_RETURNS["first_segment_return"]) not in refused.text
    assert "content-disposition" not in refused.headers
    assert snapshot(session) == before
    # An operator who is a labeller (not only the settings' token) may.
    response = client.get("/api/export?format=csv", headers=bearer(boss))
    assert response.status_code == 200 and response.text.startswith("schema_version,")
    assert snapshot(session) == before


def test_the_server_starts_without_loading_pyarrow_or_pandas() -> None:
    probe = (
        "import sys, server.app; server.app.create_app; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'pyarrow', 'pandas'}))"
    )
    root = Path(__file__).resolve().parents[2]
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=root
    )
    assert result.stdout.strip() == "[]"

"""The whole loop through the labeller API: an operator creates a run over REST, the worker
pushes queries with real clips, a labeller answers over REST, the reward model trains on those
answers, and the export lists them."""

from __future__ import annotations

import json
from pathlib import Path

from fastapi.testclient import TestClient
from worker_helpers import (
    RUN,
    SCREEN,
    database,
    decisions,
    round_accuracies,
    run_row,
    settle_labels,
    shadow_choices,
    standalone_run,
    start_worker,
    worker_config,
)

from labelqueue import RunStatus
from server.app import create_app
from server.settings import Settings

OPERATOR = {"Authorization": "Bearer full-loop-operator-token"}


def test_people_label_over_rest_and_the_run_learns_from_them(tmp_path: Path) -> None:
    url, sessions = database(tmp_path)
    data = tmp_path / "data"
    settings = Settings(database_url=url, data_dir=data,
                        operator_token=OPERATOR["Authorization"].removeprefix("Bearer "),
                        secret_key="full-loop-secret-key-0123",
                        lease_per_s=1000.0, lease_burst=1000)  # scripted, full speed
    with TestClient(create_app(settings)) as client:
        made = client.post("/api/labellers", json={"name": "bob"}, headers=OPERATOR)
        bob = {"Authorization": f"Bearer {made.json()['token']}"}
        body = {k: RUN[k] for k in ("task", "algo", "preset", "seed", "budget", "teacher_params",
                                    "config")} | {"teacher": "human"}
        created = client.post("/api/runs", json=body, headers=OPERATOR)
        assert created.status_code == 201, created.text
        run_id = created.json()["id"]

        worker = start_worker(worker_config(url, data))
        answered = 0
        while worker.is_alive() or answered < 20:
            nxt = client.get("/api/label/next", headers=bob)
            if nxt.status_code == 204:
                worker.join(timeout=0.1)
                if not worker.is_alive():
                    break
                continue
            assert nxt.status_code == 200, nxt.text
            query = nxt.json()
            assert "first_segment_return" not in query and "model_p" not in query
            left = client.get(query["left_clip_url"])  # what the <video> tag fetches
            assert left.status_code == 200 and left.content[4:8] == b"ftyp"  # an mp4
            # Bob prefers what the scripted teacher would, in screen terms.
            shadow = shadow_choices(sessions, run_id)[query["query_id"]]
            choice = SCREEN[shadow]
            if not query["left_is_first"]:
                choice = {"left": "right", "right": "left"}.get(choice, choice)
            posted = client.post(f"/api/label/{query['query_id']}", headers=bob, json={
                "choice": choice, "left_is_first": query["left_is_first"],
                "shown_at": "2026-11-21T12:00:00Z"})
            assert posted.status_code == 201, posted.text
            assert posted.json()["answer"] == shadow
            settle_labels(sessions, run_id)  # as if bob's undo window had passed
            answered += 1
        worker.join(timeout=60)

        assert answered == 20
        assert client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()["status"] == "finished"
        rounds = client.get(f"/api/runs/{run_id}/metrics?stream=rounds", headers=OPERATOR).json()
        assert [r["values"]["labels_used"] for r in rounds] == [10, 20]
        assert all(r["values"]["shadow_agreement"] == 1.0 for r in rounds)

        export = client.get(f"/api/export?format=jsonl&run_id={run_id}", headers=OPERATOR)
        assert export.status_code == 200
        rows = [json.loads(line) for line in export.text.splitlines()]
        assert len(rows) == 20 and {r["labeller_name"] for r in rows} == {"bob"}
        assert {r["source"] for r in rows} == {"human"}
        assert all(r["agrees_with_shadow"] for r in rows)

    # Bob's answers were the scripted teacher's, so the run learned what a standalone run does.
    assert run_row(sessions, run_id).status is RunStatus.FINISHED
    run_dir = data / "runs" / f"run-{run_id}"
    reference = standalone_run(tmp_path / "reference")
    assert decisions(run_dir) == decisions(reference)
    assert round_accuracies(run_dir) == round_accuracies(reference)

"""A labeller's view of gold pairs and ordinary ones carries no signal: a real run taught by
people with gold pairs, labelled over the REST API, where each labeller records what they see.
Ids: the gold pairs are at random places among their round's queries, not a block after them.
Order: each labeller is served ids in increasing order, gold pairs included. Timing: clips are
attached in id order, so a gold pair becomes servable in its place like any other. Body: the
same fields, URL shapes and clip headers."""

from __future__ import annotations

import re
import time
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import select
from worker_helpers import (
    RUN,
    SCREEN,
    database,
    run_row,
    settle_labels,
    shadow_choices,
    start_worker,
    worker_config,
)

import trainer.queue_hooks
from labelqueue import Query, RunStatus, create_run, set_clips
from server.app import create_app
from server.settings import Settings

OPERATOR_TOKEN = "gold-test-operator-token-0123"
CLIP_URL = re.compile(r"^/api/clips/(\d+)/(first|second)\?expires=\d+&sig=[0-9a-f]{64}$")


def test_a_labellers_view_tells_gold_pairs_from_the_others_in_no_way(tmp_path: Path,
                                                                      monkeypatch) -> None:
    url, sessions = database(tmp_path)
    data = tmp_path / "data"
    config = RUN["config"] | {"feedback.gold_rate": 0.3, "feedback.practice_pairs": 0}
    with sessions() as session:
        run = create_run(session, name="gold", teacher="human", **RUN | {"config": config})
    attached: list[int] = []  # the order the worker attaches clips in

    def attach(session, *, query_id, first_clip, second_clip):  # type: ignore[no-untyped-def]
        attached.append(query_id)
        return set_clips(session, query_id=query_id, first_clip=first_clip,
                         second_clip=second_clip)

    monkeypatch.setattr(trainer.queue_hooks, "set_clips", attach)
    settings = Settings(database_url=url, data_dir=data, operator_token=OPERATOR_TOKEN,
                        secret_key="gold-test-secret-key-0123",
                        lease_per_s=1000.0, lease_burst=1000)  # scripted, full speed
    seen: dict[str, list[dict]] = {}
    clip_headers: dict[int, set[str]] = {}
    with TestClient(create_app(settings)) as client:
        worker = start_worker(worker_config(url, data))  # after the app's migration: one at once
        operator = {"Authorization": f"Bearer {OPERATOR_TOKEN}"}
        tokens = {name: client.post("/api/labellers", json={"name": name},
                                    headers=operator).json()["token"]
                  for name in ("ann", "bob", "cy")}
        while worker.is_alive():
            for name, token in tokens.items():
                me = {"Authorization": f"Bearer {token}"}
                shown = client.get(f"/api/label/next?run_id={run.id}", headers=me)
                if shown.status_code == 204:
                    continue
                body = shown.json()
                seen.setdefault(name, []).append(body)
                for side in ("left_clip_url", "right_clip_url"):
                    clip = client.get(body[side])
                    assert clip.status_code == 200
                    clip_headers[body["query_id"]] = set(clip.headers) - {"content-length"}
                truth = shadow_choices(sessions, run.id)[body["query_id"]]
                answer = {"choice": SCREEN[truth], "left_is_first": True,
                          "shown_at": body["lease_expires_at"]}
                if not body["left_is_first"]:  # the server put the second segment left
                    answer["choice"] = {"left": "right", "right": "left"}.get(
                        answer["choice"], answer["choice"])
                    answer["left_is_first"] = False
                posted = client.post(f"/api/label/{body['query_id']}", json=answer, headers=me)
                assert posted.status_code == 201, posted.text
                settle_labels(sessions, run.id)
            time.sleep(0.05)
    worker.join(timeout=60)
    assert run_row(sessions, run.id).status is RunStatus.FINISHED
    with sessions() as session:
        rows = session.execute(select(Query.id, Query.round, Query.gold)
                               .where(Query.run_id == run.id).order_by(Query.id)).all()
    gold = {i for i, _, is_gold in rows if is_gold}
    assert len(gold) == 10 and len(rows) == 30  # 5 gold pairs in each of the two rounds

    # Ids: in each round, gold pairs are among the queries, not a block after them.
    for round_ in (0, 1):
        ids = [(i, is_gold) for i, r, is_gold in rows if r == round_]
        last_ordinary = max(i for i, is_gold in ids if not is_gold)
        assert any(i < last_ordinary for i, is_gold in ids if is_gold), ids
    # Timing: the clips came in id order, gold pairs in their places.
    assert attached == sorted(attached) and set(attached) == {i for i, _, _ in rows}
    # Order: every labeller was served increasing ids, gold pairs included.
    served_gold = set()
    for name, bodies in seen.items():
        ids = [b["query_id"] for b in bodies]
        assert ids == sorted(set(ids)), (name, ids)
        served_gold |= gold & set(ids)
    assert served_gold, "no labeller was served a gold pair"
    # Body: the same fields and values of the same kinds; clip URLs and responses alike.
    bodies = [b for name in seen for b in seen[name]]
    shape = {(k, type(v).__name__) for k, v in bodies[0].items()}
    for b in bodies:
        assert {(k, type(v).__name__) for k, v in b.items()} == shape
        assert b["practice"] is None
        for side in ("left_clip_url", "right_clip_url"):
            match = CLIP_URL.match(b[side])
            assert match is not None and int(match.group(1)) == b["query_id"], b[side]
    assert len({frozenset(h) for h in clip_headers.values()}) == 1

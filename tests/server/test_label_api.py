"""The labeller's path: lease a query, watch its clips, answer it; and every way it can fail."""

from __future__ import annotations

import json
import threading
from datetime import UTC, datetime, timedelta
from typing import Any

from fastapi.testclient import TestClient
from server_helpers import (
    OPERATOR,
    bearer,
    new_labeller,
    new_run,
    running_run_with_queries,
    snapshot,
)
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from labelqueue import Label, Query, set_labeller_active
from server.app import create_app
from server.settings import Settings

NEXT_KEYS = {
    "query_id",
    "run_id",
    "lease_expires_at",
    "left_clip_url",
    "right_clip_url",
    "left_is_first",
    "segment_length",
    "left_start_step",  # where each clip starts in its episode: shown by the player
    "right_start_step",
    "practice",  # null but on a practice pair (feedback.practice_pairs)
}


def shown_at() -> str:
    return datetime.now(UTC).isoformat()


def label_count(session: Session) -> int:
    count = session.scalar(select(func.count()).select_from(Label))
    session.commit()
    return int(count or 0)


def test_a_labeller_answers_each_query_once_and_then_has_nothing_to_do(
    client: TestClient, session: Session, settings: Settings, secret_returns: dict[str, float]
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    run_id, query_ids = running_run_with_queries(client, session, settings)

    response = client.get("/api/label/next", headers=alice)
    assert response.status_code == 200, response.text
    shown = response.json()
    assert set(shown) == NEXT_KEYS
    assert shown["query_id"] == query_ids[0] and shown["run_id"] == run_id
    # No ground truth anywhere in what the browser gets, under any name.
    for value in secret_returns.values():
        assert str(value) not in response.text
    assert not {"return", "model_p", "score", "rule"} & set(json.dumps(shown).split('"'))

    # The clips come from the signed URLs alone (a <video> tag sends no Authorization header).
    left, right = client.get(shown["left_clip_url"]), client.get(shown["right_clip_url"])
    assert left.status_code == right.status_code == 200
    assert left.headers["content-type"] == "video/mp4"
    left_side = "a" if shown["left_is_first"] else "b"
    assert left.content.startswith(f"fake mp4 run{run_id}/q{query_ids[0]}-{left_side}".encode())
    assert left.content != right.content

    # A browser seeking in the video asks for a byte range.
    partial = client.get(shown["left_clip_url"], headers={"Range": "bytes=5-14"})
    assert partial.status_code == 206 and partial.content == left.content[5:15]

    # A page reload keeps the same query and the same sides.
    again = client.get("/api/label/next", headers=alice).json()
    assert again["query_id"] == shown["query_id"]
    assert again["left_is_first"] == shown["left_is_first"]

    body = {"choice": "left", "left_is_first": shown["left_is_first"], "shown_at": shown_at()}
    first = client.post(f"/api/label/{shown['query_id']}", json=body, headers=alice)
    assert first.status_code == 201, first.text
    label = first.json()
    assert label["choice"] == "left"
    assert label["answer"] == ("first" if shown["left_is_first"] else "second")

    repeat = client.post(f"/api/label/{shown['query_id']}", json=body, headers=alice)
    assert repeat.status_code == 200 and repeat.json() == label
    assert label_count(session) == 1
    run = client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()
    assert run["labels_used"] == 1

    second = client.get("/api/label/next", headers=alice)
    assert second.status_code == 200 and second.json()["query_id"] == query_ids[1]
    body["left_is_first"] = second.json()["left_is_first"]
    assert client.post(f"/api/label/{query_ids[1]}", json=body, headers=alice).status_code == 201

    done = client.get("/api/label/next", headers=alice)
    assert done.status_code == 204 and done.content == b""
    assert client.get(f"/api/label/next?run_id={run_id}", headers=alice).status_code == 204


def test_a_label_for_an_expired_lease_is_refused_and_changes_nothing(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    running_run_with_queries(client, session, settings, n=1)
    shown = client.get("/api/label/next", headers=alice).json()
    session.execute(
        update(Query)
        .where(Query.id == shown["query_id"])
        .values(lease_expires_at=datetime.now(UTC) - timedelta(seconds=1))
    )
    session.commit()
    before = snapshot(session)

    body = {"choice": "right", "left_is_first": shown["left_is_first"], "shown_at": shown_at()}
    response = client.post(f"/api/label/{shown['query_id']}", json=body, headers=alice)
    assert response.status_code == 409
    assert "expired" in response.json()["detail"]
    assert snapshot(session) == before


def test_a_label_for_another_labellers_query_is_refused_and_changes_nothing(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    bob = bearer(new_labeller(client, "bob"))
    running_run_with_queries(client, session, settings, n=1)
    shown = client.get("/api/label/next", headers=alice).json()
    # Bob finds nothing: the only query is Alice's while her lease lasts.
    assert client.get("/api/label/next", headers=bob).status_code == 204
    before = snapshot(session)

    body = {"choice": "left", "left_is_first": True, "shown_at": shown_at()}
    response = client.post(f"/api/label/{shown['query_id']}", json=body, headers=bob)
    assert response.status_code == 409
    assert "leased to another labeller" in response.json()["detail"]
    assert snapshot(session) == before


def test_malformed_or_misdirected_labels_are_refused_and_change_nothing(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    running_run_with_queries(client, session, settings, n=1)
    query_id = client.get("/api/label/next", headers=alice).json()["query_id"]
    before = snapshot(session)
    good = {"choice": "left", "left_is_first": True, "shown_at": shown_at()}

    for body, field in [
        (good | {"choice": "top"}, "choice"),
        (good | {"left_is_first": "sometimes"}, "left_is_first"),
        (good | {"shown_at": "yesterday"}, "shown_at"),
        (good | {"score": 1.0}, "score"),
    ]:
        response = client.post(f"/api/label/{query_id}", json=body, headers=alice)
        assert response.status_code == 422, body
        assert any(field in error["loc"] for error in response.json()["detail"]), response.text
    response = client.post("/api/label/999", json=good, headers=alice)
    assert response.status_code == 404 and "query 999" in response.json()["detail"]
    assert snapshot(session) == before


def test_next_query_names_unknown_and_scripted_runs(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    unknown = client.get("/api/label/next?run_id=42", headers=alice)
    assert unknown.status_code == 404 and "run 42" in unknown.json()["detail"]
    scripted = new_run(client, teacher="scripted", teacher_params={"eps": 0.1})
    response = client.get(f"/api/label/next?run_id={scripted['id']}", headers=alice)
    assert response.status_code == 409 and "scripted" in response.json()["detail"]


def test_clips_need_a_valid_signature_or_token_and_never_leave_the_clips_folder(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    run_id, (query_id,) = running_run_with_queries(client, session, settings, n=1)
    url = client.get("/api/label/next", headers=alice).json()["left_clip_url"]
    path, _, params = url.partition("?")
    expires, sig = (pair.split("=")[1] for pair in params.split("&"))

    tampered = client.get(
        f"{path}?expires={expires}&sig={sig[:-1]}{'0' if sig[-1] != '0' else '1'}"
    )
    assert tampered.status_code == 403 and "signature" in tampered.json()["detail"]
    stretched = client.get(f"{path}?expires={int(expires) + 3600}&sig={sig}")
    assert stretched.status_code == 403
    other_side = (
        path.replace("first", "second") if "first" in path else path.replace("second", "first")
    )
    assert client.get(f"{other_side}?expires={expires}&sig={sig}").status_code == 403
    past = client.get(f"{path}?expires=1000&sig={sig}")
    assert past.status_code == 403
    foreign = client.get(f"{path}?expires={expires}&sig=%C2%80{sig[2:]}")  # a non-ASCII sig
    assert foreign.status_code == 403 and "signature" in foreign.json()["detail"]

    assert client.get(path).status_code == 401
    assert client.get(path, headers=bearer("1.wrong")).status_code == 401
    assert client.get(path, headers=alice).status_code == 200
    assert client.get(path, headers=OPERATOR).status_code == 200

    for bad in ["third", "..", "%2e%2e", "first%2F..%2F..%2Fqueue.db"]:
        response = client.get(f"/api/clips/{query_id}/{bad}", headers=alice)
        assert response.status_code == 404, bad
    assert client.get("/api/clips/999/first", headers=alice).status_code == 404

    # A stored key that escapes the clips folder (written behind the queue's back) is refused,
    # and so is a link inside the folder that points outside it.
    outside = settings.data_dir / "outside.mp4"
    outside.write_bytes(b"not a clip")
    (settings.clips_root / "link.mp4").symlink_to(outside)
    for key in ["../outside.mp4", "/etc/passwd", "link.mp4", f"run{run_id}/missing.mp4"]:
        session.execute(update(Query).where(Query.id == query_id).values(first_clip=key))
        session.commit()
        response = client.get(f"/api/clips/{query_id}/first", headers=alice)
        assert response.status_code == 404, key
        assert f"query {query_id}" in response.json()["detail"]


def test_a_query_without_clips_is_not_served_to_people(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    _, (query_id,) = running_run_with_queries(client, session, settings, n=1)
    session.execute(update(Query).values(first_clip=None, second_clip=None))
    session.commit()
    assert client.get("/api/label/next", headers=alice).status_code == 204
    response = client.get(f"/api/clips/{query_id}/first", headers=alice)
    assert response.status_code == 404 and "not rendered" in response.json()["detail"]


def test_a_revoked_labeller_cannot_take_work_even_while_its_token_is_cached(
    client: TestClient, session: Session, settings: Settings
) -> None:
    running_run_with_queries(client, session, settings, n=2)
    token = new_labeller(client, "mallory")
    first = client.get("/api/label/next", headers=bearer(token))
    assert first.status_code == 200
    labeller_id = int(token.split(".")[0])
    # Revoked by another process: this server still trusts the token for a few seconds...
    set_labeller_active(session, labeller_id=labeller_id, active=False)
    before = snapshot(session)
    # ...but leasing and answering read `active` in their own transaction.
    refused = client.get("/api/label/next", headers=bearer(token))
    assert refused.status_code == 403 and "deactivated" in refused.json()["detail"]
    body = {"choice": "left", "shown_at": shown_at()}
    body["left_is_first"] = first.json()["left_is_first"]
    answer = client.post(f"/api/label/{first.json()['query_id']}", json=body, headers=bearer(token))
    assert answer.status_code == 403 and "deactivated" in answer.json()["detail"]
    assert snapshot(session) == before  # no label stored, no budget spent


def test_without_the_auth_cache_a_revoked_token_is_refused_at_once(
    settings: Settings, session: Session
) -> None:
    uncached = settings.model_copy(update={"auth_cache_seconds": 0.0})
    with TestClient(create_app(uncached)) as client:
        token = new_labeller(client, "trent")
        assert client.get("/api/label/count", headers=bearer(token)).status_code == 200
        set_labeller_active(session, labeller_id=int(token.split(".")[0]), active=False)
        assert client.get("/api/label/count", headers=bearer(token)).status_code == 401


def test_an_answer_after_the_run_was_stopped_is_refused_and_earlier_answers_stay(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    bob = bearer(new_labeller(client, "bob"))
    run_id, query_ids = running_run_with_queries(client, session, settings, n=2)
    shown_a = client.get("/api/label/next", headers=alice).json()
    shown_b = client.get("/api/label/next", headers=bob).json()
    body = {"choice": "left", "shown_at": shown_at()}
    answered = client.post(
        f"/api/label/{shown_a['query_id']}",
        json=body | {"left_is_first": shown_a["left_is_first"]},
        headers=alice,
    )
    assert answered.status_code == 201

    assert client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).json()["status"] == "stopping"
    before = snapshot(session)
    late = client.post(
        f"/api/label/{shown_b['query_id']}",
        json=body | {"left_is_first": shown_b["left_is_first"]},
        headers=bob,
    )
    assert late.status_code == 409
    assert late.json()["detail"] == f"run {run_id} is stopping: it takes no more answers"
    assert snapshot(session) == before
    run = client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()
    assert run["labels_used"] == 1  # the answer given before the stop, kept


def test_an_answer_with_another_side_order_than_shown_is_refused(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    running_run_with_queries(client, session, settings, n=1)
    shown = client.get("/api/label/next", headers=alice).json()
    before = snapshot(session)
    flipped = {"choice": "left", "shown_at": shown_at()}
    flipped["left_is_first"] = not shown["left_is_first"]
    response = client.post(f"/api/label/{shown['query_id']}", json=flipped, headers=alice)
    assert response.status_code == 422
    assert "side order" in response.json()["detail"] and "reload" in response.json()["detail"]
    assert snapshot(session) == before  # nothing stored with its answer flipped

    honest = flipped | {"left_is_first": shown["left_is_first"]}
    stored = client.post(f"/api/label/{shown['query_id']}", json=honest, headers=alice).json()
    assert stored["answer"] == ("first" if shown["left_is_first"] else "second")


def test_shown_at_outside_the_lease_is_clamped_and_an_overflowing_one_refused(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    run_id, _ = running_run_with_queries(client, session, settings, n=3)

    def answer(when: str, shown: dict[str, Any] | None = None) -> Any:
        shown = shown or client.get("/api/label/next", headers=alice).json()
        body = {"choice": "equal", "left_is_first": shown["left_is_first"], "shown_at": when}
        return client.post(f"/api/label/{shown['query_id']}", json=body, headers=alice)

    leased = datetime.now(UTC)
    held = client.get("/api/label/next", headers=alice).json()
    before = snapshot(session)
    overflowing = answer("9999-12-31T23:59:59-16:09", held)
    assert overflowing.status_code == 422
    assert "out of range" in json.dumps(overflowing.json()["detail"])
    assert snapshot(session) == before

    past = answer("1999-01-01T00:00:00Z", held).json()
    future = answer((datetime.now(UTC) + timedelta(days=2)).isoformat()).json()
    for label in (past, future):
        shown_time = datetime.fromisoformat(label["shown_at"])
        assert leased - timedelta(seconds=1) <= shown_time <= datetime.fromisoformat(
            label["answered_at"]
        )
    assert future["shown_at"] == future["answered_at"]
    # So the median answer time stays a time a person took, not years or a negative time.
    stats = client.get(f"/api/runs/{run_id}/throughput", headers=OPERATOR).json()
    assert 0 <= stats["median_answer_s"] < 60


def test_the_server_decides_the_sides_without_the_pages_echo(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    running_run_with_queries(client, session, settings, n=1)
    shown = client.get("/api/label/next", headers=alice).json()
    posted = client.post(f"/api/label/{shown['query_id']}", headers=alice,
                         json={"choice": "left", "shown_at": shown_at()})
    assert posted.status_code == 201, posted.text
    label = posted.json()
    assert label["left_is_first"] == shown["left_is_first"]
    assert label["answer"] == ("first" if shown["left_is_first"] else "second")


def test_asking_for_a_run_that_is_missing_or_scripted_says_so_and_leases_nothing(
    client: TestClient, session: Session, settings: Settings
) -> None:
    alice = bearer(new_labeller(client, "alice"))
    scripted = new_run(client, teacher="scripted")["id"]
    before = snapshot(session)

    missing = client.get("/api/label/next?run_id=999", headers=alice)
    assert missing.status_code == 404 and missing.json()["detail"] == "run 999 does not exist"
    refused = client.get(f"/api/label/next?run_id={scripted}", headers=alice)
    assert refused.status_code == 409
    assert refused.json()["detail"] == (
        f"run {scripted} is taught by a scripted teacher, not by people"
    )
    assert snapshot(session) == before


def test_a_label_request_waits_for_a_worker_writing_while_the_server_serves_others(
    client: TestClient, session: Session, settings: Settings
) -> None:
    """The label API's work runs on the event loop only when SQLite's write lock is free at
    once; while another process (here an engine of its own) writes, it waits on the label
    thread, and the loop goes on serving."""
    alice = bearer(new_labeller(client, "alice"))
    run_id, query_ids = running_run_with_queries(client, session, settings)
    answers: dict[str, Any] = {}
    asking = threading.Thread(
        target=lambda: answers.update(next=client.get("/api/label/next", headers=alice))
    )
    with session.get_bind().connect() as worker, worker.begin():  # type: ignore[union-attr]
        asking.start()
        asking.join(timeout=0.5)
        assert asking.is_alive()  # waiting for the write lock
        assert client.get("/healthz").status_code == 200
        assert client.get(f"/api/runs/{run_id}", headers=OPERATOR).status_code == 200
    asking.join(timeout=30)
    assert answers["next"].status_code == 200, answers["next"].text
    assert answers["next"].json()["query_id"] == query_ids[0]

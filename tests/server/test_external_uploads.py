"""Uploaded clips no pair names are deleted (`server.upload_sweep`): a day after their last
upload, or soon after their run stops; a clip a pair names never is. A withdrawn pair names
none: its clips go with the withdrawal."""

from __future__ import annotations

import os
import time
from pathlib import Path

from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller
from sqlalchemy.orm import Session
from test_external_api import external_run, frames, pair, upload

from externalruns.pairs import PairSpec, push_pairs, withdraw_pair
from server.app import create_app
from server.routes.external import stored_clip
from server.settings import Settings
from server.upload_sweep import sweep_uploads

DAY = 24 * 3600.0


def files(settings: Settings, run_id: int) -> set[str]:
    folder = settings.clips_root / "external" / str(run_id)
    return {path.name for path in folder.iterdir() if path.name != ".lock"}


def test_an_unused_upload_goes_a_day_after_its_last_upload_and_a_used_one_stays(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b, c = (upload(client, run_id, auth, frames(seed)) for seed in (1, 2, 3))
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("ab", a, b)]}).status_code == 201
    kept = {f"{clip}.{kind}" for clip in (a, b) for kind in ("mp4", "json")}
    assert sweep_uploads(session, settings).marked == 0  # nothing is a day old
    later = time.time() + DAY + 60
    assert sweep_uploads(session, settings, now=later).marked == 1
    # From the first sweep on, no pair can name it; the second deletes it.
    refused = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [pair("ac", a, c)]})
    assert refused.status_code == 422 and "no clip uploaded" in refused.json()["detail"]
    assert sweep_uploads(session, settings, now=later).deleted == 1
    assert files(settings, run_id) == kept
    shown = client.get(f"/api/label/next?run_id={run_id}",
                       headers=bearer(new_labeller(client, "ann"))).json()
    assert client.get(shown["left_clip_url"]).status_code == 200  # a used clip stays
    # Uploaded again, it is a new upload, counted from now.
    assert upload(client, run_id, auth, frames(3)) == c
    assert sweep_uploads(session, settings).marked == 0
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("ac", a, c)]}).status_code == 201


def test_a_withdrawn_pairs_clips_are_deleted_and_served_no_more(
    client: TestClient, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    pushed = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("oops", a, b), pair("kept", b, b)]}).json()
    oops, _ = (item["query_id"] for item in pushed["pairs"])
    token = bearer(new_labeller(client, "ann"))
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
    assert shown["query_id"] == oops  # on ann's screen when its client withdraws it
    url = f"/api/runs/{run_id}/pairs/{oops}/withdraw"
    assert client.post(url, headers=auth).status_code == 200
    # Its own clip goes, note and all; the one another pair still shows stays.
    assert files(settings, run_id) == {f"{b}.mp4", f"{b}.json"}
    gone = client.get(shown["left_clip_url" if shown["left_is_first"] else "right_clip_url"])
    assert gone.status_code == 404, gone.text
    assert client.get(f"/api/clips/{oops}/first", headers=OPERATOR).status_code == 404
    # Withdrawn again, with its clip already gone: the same answer, nothing else deleted.
    again = client.post(url, headers=auth)
    assert again.status_code == 200 and again.json()["withdrawn"], again.text
    assert files(settings, run_id) == {f"{b}.mp4", f"{b}.json"}
    # A deleted clip is named by no new pair until it is uploaded again.
    refused = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [pair("again", a, b)]})
    assert refused.status_code == 422 and "no clip uploaded" in refused.json()["detail"]
    assert upload(client, run_id, auth, frames(1)) == a
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("again", a, b)]}).status_code == 201


def test_a_withdrawn_pair_pushed_again_comes_back_withdrawn_though_its_clips_are_gone(
    client: TestClient, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    body = {"pairs": [pair("oops", a, b)]}
    [pushed] = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json=body).json()["pairs"]
    url = f"/api/runs/{run_id}/pairs/{pushed['query_id']}/withdraw"
    assert client.post(url, headers=auth).status_code == 200
    assert files(settings, run_id) == set()
    # A retry of the first push (its answer lost on the way) is answered as any push of a
    # stored key: its query, not created, and nothing is stored.
    again = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json=body)
    assert again.status_code == 200, again.text
    assert again.json()["pairs"] == [{"key": "oops", "query_id": pushed["query_id"],
                                      "created": False}]
    state = client.get(f"/api/runs/{run_id}/pairs", headers=auth, params={"key": "oops"})
    assert state.json()["pairs"][0]["withdrawn"]
    # Beside a new pair, the new pair still needs its clips uploaded.
    refused = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [pair("oops", a, b), pair("new", b, a)]})
    assert refused.status_code == 422 and "pairs[1] ('new')" in refused.json()["detail"]

def test_the_sweep_takes_a_withdrawn_pairs_clips_the_withdrawal_left(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    [pushed] = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                           json={"pairs": [pair("ab", a, b)]}).json()["pairs"]
    # Withdrawn in the database, its files not deleted (the server stopped in between).
    withdraw_pair(session, run_id=run_id, query_id=pushed["query_id"])
    later = time.time() + DAY + 60
    assert sweep_uploads(session, settings, now=later).marked == 2
    assert sweep_uploads(session, settings, now=later).deleted == 2
    assert files(settings, run_id) == set()


def test_uploading_a_clip_again_keeps_it_from_the_sweep(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    clip = upload(client, run_id, auth, frames(1))
    note = settings.clips_root / "external" / str(run_id) / f"{clip}.json"
    old = time.time() - DAY - 60
    os.utime(note, (old, old))
    assert upload(client, run_id, auth, frames(1)) == clip  # the same bytes: 200, not stored
    assert sweep_uploads(session, settings).marked == 0
    assert sweep_uploads(session, settings, now=time.time() + DAY + 60).marked == 1
    # Uploaded again between the two sweeps: stored again, and the second sweep keeps it.
    again = client.post(f"/api/runs/{run_id}/clips", content=frames(1),
                        headers=auth | {"content-type": "application/x-npy"})
    assert again.status_code == 201
    swept = sweep_uploads(session, settings)
    assert (swept.deleted, swept.kept) == (0, 1)
    assert files(settings, run_id) == {f"{clip}.mp4", f"{clip}.json"}


def test_a_push_under_way_when_the_sweep_marks_its_clip_keeps_it(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    known = {clip: stored_clip(settings, run_id, clip) for clip in (a, b)}  # the push read them
    sweep_uploads(session, settings, now=time.time() + DAY + 60)
    assert stored_clip(settings, run_id, a) is None
    push_pairs(session, run_id=run_id, pairs=[PairSpec("ab", a, b)],  # ... then committed
               clips={clip: info for clip, info in known.items() if info is not None})
    swept = sweep_uploads(session, settings, now=time.time() + DAY + 60)
    assert (swept.deleted, swept.kept) == (0, 2)
    assert stored_clip(settings, run_id, a) is not None
    shown = client.get(f"/api/label/next?run_id={run_id}",
                       headers=bearer(new_labeller(client, "bob"))).json()
    assert client.get(shown["right_clip_url"]).status_code == 200


def test_a_stopped_runs_unused_uploads_go_at_once_and_a_requeued_run_uploads_again(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [pair("aa", a, a)]})
    other, other_auth = external_run(client)
    untouched = upload(client, other, other_auth, frames(2))
    folder = settings.clips_root / "external" / str(run_id)
    leftover, fresh = folder / f".{b}.0123abcd.tmp.mp4", folder / f".{b}.4567cdef.tmp.mp4"
    for path in (leftover, fresh):
        path.write_bytes(b"cut short")
    os.utime(leftover, (time.time() - 7200, time.time() - 7200))
    assert client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).status_code == 200
    sweep_uploads(session, settings)
    sweep_uploads(session, settings)
    assert files(settings, run_id) == {f"{a}.mp4", f"{a}.json", fresh.name}
    assert stored_clip(settings, other, untouched) is not None  # a running run's, a minute old
    assert client.post(f"/api/runs/{run_id}/requeue", headers=OPERATOR).status_code == 200
    assert upload(client, run_id, auth, frames(2)) == b
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("ab", a, b)]}).status_code == 201


def test_the_server_sweeps_on_its_own(settings: Settings, tmp_path: Path) -> None:
    quick = settings.model_copy(update={"upload_sweep_seconds": 0.2,
                                        "unused_upload_hours": 0.5 / 3600})
    with TestClient(create_app(quick)) as client:
        run_id, auth = external_run(client)
        clip = upload(client, run_id, auth, frames(1))
        deadline = time.monotonic() + 10
        while stored_clip(quick, run_id, clip) is not None and time.monotonic() < deadline:
            time.sleep(0.1)
        while files(quick, run_id) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert files(quick, run_id) == set()

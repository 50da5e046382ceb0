"""External runs over REST: a client with a run token uploads clips, pushes pairs and reads the
answers people give on the label page; bad input is a 4xx that stores nothing."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import imageio.v2 as imageio
import numpy as np
import pytest
from database_helpers import BACKENDS, postgres_schema
from fastapi.testclient import TestClient
from server_helpers import OPERATOR, bearer, new_labeller, new_run
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from externalruns.runs import run_of_token
from labelqueue import Query, claim_run
from labelstats.calibration import calibration_report
from rundata.clip_codec import probe_clip
from rundata.export_read import read_export
from sepoa.client import Pair, Study
from server.settings import Settings

NPY = {"content-type": "application/x-npy"}
JSON_TYPE = {"content-type": "application/json"}
SECRET_ID = "client-episode-31337"


@pytest.fixture(params=BACKENDS)
def settings(request: pytest.FixtureRequest, settings: Settings) -> Iterator[Settings]:
    """The server's settings on SQLite, and on PostgreSQL too when the tests have one
    (scripts/with_postgres.sh): the answers feed's cursor relies on each's commit order."""
    if request.param == "sqlite":
        yield settings
        return
    with postgres_schema() as url:
        yield settings.model_copy(update={"database_url": url})


def frames(seed: int, count: int = 6, size: tuple[int, int] = (32, 48)) -> bytes:
    """A frame array as `numpy.save` writes it."""
    array = np.random.default_rng(seed).integers(0, 255, (count, *size, 3), dtype=np.uint8)
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def external_run(client: TestClient, **body: Any) -> tuple[int, dict[str, str]]:
    """An external run and its client's auth header."""
    response = client.post("/api/runs/external", headers=OPERATOR,
                           json={"task": "gym:HalfCheetah-v5", "budget": 10} | body)
    assert response.status_code == 201, response.text
    run_id = response.json()["id"]
    token = client.post(f"/api/runs/{run_id}/tokens", headers=OPERATOR)
    assert token.status_code == 201, token.text
    return run_id, bearer(token.json()["token"])


def upload(client: TestClient, run_id: int, auth: dict[str, str], body: bytes,
           content_type: str = "application/x-npy") -> str:
    response = client.post(f"/api/runs/{run_id}/clips", content=body,
                           headers=auth | {"content-type": content_type})
    assert response.status_code in (200, 201), response.text
    clip_id: str = response.json()["clip_id"]
    return clip_id


def pair(key: str, first: str, second: str, **extra: Any) -> dict[str, Any]:
    return {"key": key, "first_clip": first, "second_clip": second} | extra


def answer(client: TestClient, token: dict[str, str], shown: dict[str, Any],
           click: str) -> Any:
    return client.post(f"/api/label/{shown['query_id']}", headers=token, json={
        "choice": click, "left_is_first": shown["left_is_first"],
        "shown_at": datetime.now(UTC).isoformat()})


def queries(session: Session) -> int:
    count = session.scalar(select(func.count()).select_from(Query)) or 0
    session.commit()
    return count


def test_pushed_frames_are_labelled_on_the_label_page_and_the_answers_come_back(
    client: TestClient, session: Session, settings: Settings
) -> None:
    run_id, auth = external_run(client, labels_per_query=2)
    first, second = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth,
                                                                    frames(2))
    pushed = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [pair(
        "ep7-vs-ep9", first, second, returns=[987.125, -654.375], meta={"ids": [SECRET_ID]})]})
    assert pushed.status_code == 201, pushed.text
    [query] = pushed.json()["pairs"]
    assert claim_run(session, worker_id="w") is None  # no worker ever trains it
    given = {}
    for name, click in (("ann", "left"), ("bob", "right")):
        token = new_labeller(client, name)
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token))
        assert shown.status_code == 200, shown.text
        assert shown.json()["query_id"] == query["query_id"]
        # The hidden metadata never reaches a labeller's browser.
        assert SECRET_ID not in shown.text and "987.125" not in shown.text
        # An uploaded clip is of no episode step the server knows: it states none.
        assert (shown.json()["left_start_step"], shown.json()["right_start_step"]) == (
            None, None)
        clip = client.get(shown.json()["left_clip_url"])
        assert clip.status_code == 200 and clip.headers["content-type"] == "video/mp4"
        path = settings.data_dir / f"{name}.mp4"
        path.write_bytes(clip.content)
        info = probe_clip(path)  # decodes whole: what the browser plays
        assert (info.codec, info.width, info.height, info.frames) == ("h264", 48, 32, 6)
        answered = answer(client, bearer(token), shown.json(), click)
        assert answered.status_code == 201, answered.text
        given[name] = answered.json()["answer"]
    feed = client.get(f"/api/runs/{run_id}/answers", headers=auth).json()
    assert [e["labeller"] for e in feed["events"]] == ["ann", "bob"]
    last = feed["events"][-1]
    assert last["key"] == "ep7-vs-ep9" and last["meta"] == {"ids": [SECRET_ID]}
    assert last["complete"] and last["k"] == 2
    assert {a["labeller"]: a["answer"] for a in last["answers"]} == given
    if given["ann"] != given["bob"]:  # one says first, the other second: an explicit tie
        assert (last["aggregate"], last["tie"]) == ("cant_tell", True)
    assert feed["open_pairs"] == 0
    run = client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()
    assert (run["labels_used"], run["status"], run["algo"]) == (2, "running", "external")


def test_a_retried_push_makes_no_second_query_and_a_reused_key_is_refused(
    client: TestClient, session: Session
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    assert upload(client, run_id, auth, frames(1)) == a  # the same bytes: the same clip
    body = {"pairs": [pair("k1", a, b), pair("k2", b, a)]}
    first = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json=body)
    again = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json=body)
    assert (first.status_code, again.status_code) == (201, 200)
    assert [p["query_id"] for p in first.json()["pairs"]] == [
        p["query_id"] for p in again.json()["pairs"]]
    assert [p["created"] for p in again.json()["pairs"]] == [False, False]
    assert queries(session) == 2
    other = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                        json={"pairs": [pair("k3", a, b), pair("k1", a, b, meta={"x": 1})]})
    assert other.status_code == 409 and "'k1' was pushed before" in other.json()["detail"]
    keyless = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [{"first_clip": a, "second_clip": b}]})
    assert keyless.status_code == 422 and keyless.json()["detail"][0]["loc"][-1] == "key"
    assert queries(session) == 2  # k3 was not stored either: all or none


def test_the_same_frames_at_another_frame_rate_are_another_clip_and_pair_with_no_other(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    url, body = f"/api/runs/{run_id}/clips", frames(1, count=30)
    uploads = [client.post(url, params={"fps": fps}, content=body, headers=auth | NPY)
               for fps in (30, 5, 30.0)]
    assert [u.status_code for u in uploads] == [201, 201, 200]
    fast, slow, again = (u.json() for u in uploads)
    assert fast["clip_id"] != slow["clip_id"] and again["clip_id"] == fast["clip_id"]
    assert (fast["seconds"], slow["seconds"]) == pytest.approx((1.0, 6.0), abs=0.05)
    # Played side by side on one clock, two clips of one pair must last as long.
    other = client.post(url, params={"fps": 5}, content=frames(2, count=30), headers=auth | NPY)
    apart = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("k", fast["clip_id"], other.json()["clip_id"])]})
    assert apart.status_code == 422 and "last 1.00 s and 6.00 s" in apart.json()["detail"]
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("k", slow["clip_id"], other.json()["clip_id"])]}).status_code == 201


def test_frames_at_a_rate_too_slow_for_the_length_limit_are_refused_before_encoding(
    client: TestClient, settings: Settings
) -> None:
    """fps is only bounded above 0: 6 frames at fps=1e-300 made ffmpeg fail (a 500), and at
    fps=0.001 they were encoded before the clip's 6 000 s were refused. Both are a 422 naming
    the length the frames would last; at the limit they are a clip."""
    run_id, auth = external_run(client)
    url = f"/api/runs/{run_id}/clips"
    for fps in (1e-300, 0.001):
        refused = client.post(url, params={"fps": fps}, content=frames(1), headers=auth | NPY)
        assert refused.status_code == 422, refused.text
        assert "6 frames at fps=" in refused.json()["detail"]
        assert "at most 60 s" in refused.json()["detail"]
    assert list((settings.clips_root / "external" / str(run_id)).iterdir()) == []
    longest = client.post(url, params={"fps": 0.1}, content=frames(1), headers=auth | NPY)
    assert longest.status_code == 201 and longest.json()["seconds"] == pytest.approx(60, abs=1)


def test_bad_clips_and_pairs_are_refused_by_name_and_nothing_is_kept(
    client: TestClient, session: Session, settings: Settings, tmp_path: Path
) -> None:
    run_id, auth = external_run(client, budget=2)
    url = f"/api/runs/{run_id}/clips"
    garbage = client.post(url, content=b"\x00\x00\x00\x18ftypmp42" + b"x" * 500,
                          headers=auth | {"content-type": "video/mp4"})
    assert garbage.status_code == 422 and "does not decode" in garbage.json()["detail"]
    mpeg4 = tmp_path / "mpeg4.mp4"
    with imageio.get_writer(mpeg4, format="FFMPEG", fps=10, codec="mpeg4",
                            macro_block_size=2) as writer:
        for frame in np.zeros((3, 32, 32, 3), np.uint8):
            writer.append_data(frame)
    codec = client.post(url, content=mpeg4.read_bytes(), headers=auth | {
        "content-type": "video/mp4"})
    assert codec.status_code == 422 and "codec is mpeg4" in codec.json()["detail"]
    wide = tmp_path / "wide.mp4"  # a video's sides are bounded as a frame array's are
    with imageio.get_writer(wide, format="FFMPEG", fps=10, codec="libx264",
                            pixelformat="yuv420p", macro_block_size=2) as writer:
        for frame in np.zeros((2, 32, 2048, 3), np.uint8):
            writer.append_data(frame)
    too_wide = client.post(url, content=wide.read_bytes(), headers=auth | {
        "content-type": "video/mp4"})
    assert too_wide.status_code == 422 and "2048x32" in too_wide.json()["detail"]
    assert "[16, 1024]" in too_wide.json()["detail"]
    odd = client.post(url, content=frames(1, size=(31, 32)), headers=auth | NPY)
    assert odd.status_code == 422 and "must be even" in odd.json()["detail"]
    flat = client.post(url, content=frames(1)[:-10], headers=auth | NPY)
    assert flat.status_code == 422 and "not a NumPy" in flat.json()["detail"]
    text = client.post(url, content=b"hello", headers=auth | {"content-type": "text/plain"})
    assert text.status_code == 415
    big = client.post(url, content=b"\0" * (settings.clip_upload_bytes + 1),
                      headers=auth | {"content-type": "video/mp4"})
    assert big.status_code == 413
    folder = settings.clips_root / "external" / str(run_id)
    assert not folder.exists() or list(folder.iterdir()) == []
    small, wide = upload(client, run_id, auth, frames(1)), upload(
        client, run_id, auth, frames(2, size=(32, 64)))
    shapes = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                         json={"pairs": [pair("k", small, wide)]})
    assert shapes.status_code == 422 and "differ in shape" in shapes.json()["detail"]
    missing = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [pair("k", small, "0" * 32)]})
    assert missing.status_code == 422 and "no clip uploaded" in missing.json()["detail"]
    wrong_gold = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("g", small, small, gold="first", returns=[1.0, 2.0])]})
    assert wrong_gold.status_code == 422 and "contradicts" in wrong_gold.json()["detail"]
    over = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair(f"k{i}", small, small) for i in range(3)]})
    assert over.status_code == 409 and "budget is 2 answers" in over.json()["detail"]
    assert queries(session) == 0


def refused_naming(client: TestClient, run_id: int, auth: dict[str, str], clip: str,
                   cases: list[tuple[str, str, str]]) -> str:
    """Push a pair of `clip` with each case's fields (raw JSON, as no Python dict holds
    them): each is a 422 whose one problem is at the field and says `said`. The pairs URL."""
    url = f"/api/runs/{run_id}/pairs"
    for field, extra, said in cases:
        body = f'{{"pairs": [{{"first_clip": "{clip}", "second_clip": "{clip}", {extra}}}]}}'
        refused = client.post(url, content=body, headers=auth | JSON_TYPE)
        assert refused.status_code == 422, (extra, refused.text)
        [problem] = refused.json()["detail"]
        assert problem["loc"][-1] == field and said in problem["msg"], (extra, problem)
    return url


def test_a_nul_a_lone_surrogate_or_a_number_json_has_not_in_a_pair_is_refused_naming_it(
    client: TestClient, session: Session
) -> None:
    """PostgreSQL stores no NUL in text and JSON has no NaN (SQLite kept it as null): such a
    key or meta is a 422 naming the field, on both databases alike. JSON's "\\ud800" escape
    alone is no character: in meta it was stored, and every read of the pair's state or
    answers failed (500) from then on; in a key, the 422 itself did."""
    run_id, auth = external_run(client)
    a = upload(client, run_id, auth, frames(1))
    url = refused_naming(client, run_id, auth, a, [
        ("key", '"key": "k\\u0000x"', "NUL character"),
        ("meta", '"key": "k", "meta": {"s": "a\\u0000b"}', "meta.s holds a NUL"),
        ("meta", '"key": "k", "meta": {"ok\\u0000": 1}', "a key of meta holds a NUL"),
        ("meta", '"key": "k", "meta": {"x": NaN}', "meta.x is nan"),
        ("meta", '"key": "k", "meta": {"ids": [1, {"r": -Infinity}]}', "meta.ids[1].r is -inf"),
        ("returns", '"key": "k", "returns": [NaN, 1.0]', "finite"),
        ("key", '"key": "k\\ud800"', "valid string"),
        ("meta", '"key": "k", "meta": {"path": "ep\\udce9.npz"}', "meta.path holds a lone"),
        ("meta", '"key": "k", "meta": {"\\udc00": 1}', "a key of meta holds a lone"),
        ("meta", '"key": "k", "meta": {"ids": [{"n": "\\ud83d"}]}', "meta.ids[0].n holds"),
    ])
    bad_key = client.get(url, params={"key": "k\x00"}, headers=auth)
    assert bad_key.status_code == 422 and "NUL character" in bad_key.text
    for field in ("task", "name"):
        made = client.post("/api/runs/external", headers=OPERATOR,
                           json={"task": "gym:HalfCheetah-v5", "budget": 10} | {field: "a\x00b"})
        assert made.status_code == 422, made.text
        [problem] = made.json()["detail"]
        assert problem["loc"][-1] == field and "NUL" in problem["msg"], problem
    assert queries(session) == 0


def test_a_lone_surrogate_in_a_task_is_a_422_and_meta_of_any_character_comes_back(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    a = upload(client, run_id, auth, frames(1))
    url = f"/api/runs/{run_id}/pairs"
    made = client.post("/api/runs/external", headers=OPERATOR | JSON_TYPE,
                       content='{"task": "cheetah \\udc80", "budget": 5}')
    assert made.status_code == 422 and made.json()["detail"][0]["loc"][-1] == "task"
    assert client.get("/api/runs/external", headers=OPERATOR).json()[1:] == []
    stored = client.post(url, headers=auth, json={"pairs": [pair("k", a, a, meta={"ep": "🐆"})]})
    assert stored.status_code == 201, stored.text
    token = new_labeller(client, "ann")
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=bearer(token)).json()
    assert answer(client, bearer(token), shown, "left").status_code == 201
    feed = client.get(f"/api/runs/{run_id}/answers", headers=auth)
    assert feed.status_code == 200 and feed.json()["events"][0]["meta"] == {"ep": "🐆"}


def test_meta_is_measured_in_the_bytes_it_takes_not_its_ascii_escapes(
    client: TestClient,
) -> None:
    """The limit is 4096 bytes of JSON: 1 500 'é' (3 000 bytes) fit, though their \\u00e9
    escapes would take 9 000 characters; 2 100 (4 200 bytes) do not."""
    run_id, auth = external_run(client)
    a = upload(client, run_id, auth, frames(1))
    url = f"/api/runs/{run_id}/pairs"
    fits = client.post(url, headers=auth, json={"pairs": [pair("k", a, a, meta={"n": "é" * 1500})]})
    assert fits.status_code == 201, fits.text
    over = client.post(url, headers=auth, json={"pairs": [pair("l", a, a, meta={"n": "é" * 2100})]})
    assert over.status_code == 422 and "larger than 4096 bytes" in over.json()["detail"]


def test_a_run_token_reaches_its_own_run_and_nothing_else(client: TestClient) -> None:
    run_id, auth = external_run(client)
    other, _ = external_run(client)
    trained = new_run(client)["id"]
    assert client.get(f"/api/runs/{other}/answers", headers=auth).status_code == 403
    assert client.post(f"/api/runs/{other}/clips", content=frames(1),
                       headers=auth | NPY).status_code == 403
    assert client.get("/api/runs", headers=auth).status_code == 401
    assert client.get("/api/label/next", headers=auth).status_code == 401
    labeller = bearer(new_labeller(client, "carol"))
    assert client.get(f"/api/runs/{run_id}/answers", headers=labeller).status_code == 403
    assert client.get(f"/api/runs/{run_id}/answers", headers=OPERATOR).status_code == 200
    assert client.post(f"/api/runs/{trained}/tokens", headers=OPERATOR).status_code == 409
    forged = bearer(auth["Authorization"].removeprefix("Bearer ")[:-2] + "xx")
    assert client.get(f"/api/runs/{run_id}/answers", headers=forged).status_code == 401


def test_a_token_id_or_cursor_of_other_digits_or_too_large_is_none(
    client: TestClient, session: Session
) -> None:
    """Only ASCII digits make an id ('²' and '١' are digits to str.isdigit, not to int()), and
    one an id column holds: a token with any other is no token (401), such a cursor no cursor
    (422 saying what one is)."""
    run_id, auth = external_run(client)
    for token in ("run.\u00b2.abc", "run.\u0661.abc", "run.2147483648.abc", "run.1e3.abc"):
        assert run_of_token(session, token=token) is None, token
    refused = client.get(f"/api/runs/{run_id}/answers",
                         headers=bearer("run.2147483648.abc"))  # too large for PostgreSQL
    assert refused.status_code == 401, refused.text
    for cursor in ("\u00b2.0", "0.\u0661", "2147483648.0"):
        read = client.get(f"/api/runs/{run_id}/answers", params={"after": cursor}, headers=auth)
        assert read.status_code == 422 and "is not one the answers feed gave" in read.text


def test_the_cursor_resumes_and_an_answer_taken_back_comes_as_a_withdrawal(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                json={"pairs": [pair("k1", a, b), pair("k2", b, a)]})
    token = bearer(new_labeller(client, "dan"))
    url = f"/api/runs/{run_id}/answers"
    started = time.monotonic()
    empty = client.get(f"{url}?wait=0.6", headers=auth).json()
    assert empty["events"] == [] and time.monotonic() - started >= 0.5  # it waited
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
    assert answer(client, token, shown, "left").status_code == 201
    # Given at once, nothing held back (on PostgreSQL too: ids commit in order).
    read = client.get(f"{url}?after={empty['cursor']}", headers=auth).json()
    assert [e["kind"] for e in read["events"]] == ["answer"]
    # The client crashed here and lost what it read: from the same cursor it reads it again.
    assert client.get(f"{url}?after={empty['cursor']}", headers=auth).json() == read
    taken = client.post(f"/api/label/{shown['query_id']}/withdraw", headers=token, json={})
    assert taken.status_code == 200, taken.text
    after = client.get(f"{url}?after={read['cursor']}", headers=auth).json()
    [event] = after["events"]
    assert (event["kind"], event["key"], event["answers"], event["aggregate"]) == (
        "withdrawal", "k1", [], None)
    assert client.get(f"{url}?after={after['cursor']}", headers=auth).json()["events"] == []
    for cursor in ("99.0", "0.5", "x"):
        future = client.get(f"{url}?after={cursor}", headers=auth)
        assert future.status_code == 422, cursor


def test_where_pairs_stand_is_read_by_their_keys_without_the_feed(client: TestClient) -> None:
    run_id, auth = external_run(client, labels_per_query=2)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("k1", a, b, meta={"ep": 3}), pair("k2", b, a)]})
    for name in ("ann", "bob"):
        token = bearer(new_labeller(client, name))
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
        assert answer(client, token, shown, "left").status_code == 201
    url = f"/api/runs/{run_id}/pairs"
    read = client.get(url, params={"key": ["k2", "nope", "k1", "k2"]}, headers=auth)
    assert read.status_code == 200, read.text
    k2, k1 = read.json()["pairs"]
    assert read.json()["unknown"] == ["nope"]
    # The fields an answers event carries for its pair, as the pair stands now.
    [event] = client.get(f"/api/runs/{run_id}/answers", headers=auth).json()["events"][-1:]
    assert k1 == {name: event[name] for name in k1} and k1["meta"] == {"ep": 3}
    assert (k1["complete"], len(k1["answers"]), k1["k"]) == (True, 2, 2)
    assert (k2["key"], k2["complete"], k2["answers"], k2["aggregate"]) == ("k2", False, [], None)
    many = client.get(url, params={"key": [f"k{i}" for i in range(101)]}, headers=auth)
    assert many.status_code == 422 and "at most 100" in many.text
    assert client.get(url, headers=auth).status_code == 422  # no key
    other, _ = external_run(client)
    assert client.get(f"/api/runs/{other}/pairs?key=k1", headers=auth).status_code == 403


def test_a_cursor_names_its_run_and_another_runs_is_refused(client: TestClient) -> None:
    """A cursor another run's feed gave would skip this run's answers below its ids: 422."""
    runs = [external_run(client) for _ in range(2)]
    for run_id, auth in runs:
        a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
        client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                    json={"pairs": [pair("k1", a, b), pair("k2", b, a)]})
    (run_a, auth_a), (run_b, auth_b) = runs
    token = bearer(new_labeller(client, "hal"))
    for run_id in (run_b, run_a, run_b):  # label ids 1 and 3 are run B's, 2 run A's
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
        assert answer(client, token, shown, "left").status_code == 201
    cursor_a = client.get(f"/api/runs/{run_a}/answers", headers=auth_a).json()["cursor"]
    assert cursor_a == f"{run_a}.2.0"
    other = client.get(f"/api/runs/{run_b}/answers", params={"after": cursor_a}, headers=auth_b)
    assert other.status_code == 422 and f"is run {run_a}'s" in other.json()["detail"]
    older = client.get(f"/api/runs/{run_b}/answers", params={"after": "2.0"}, headers=auth_b)
    assert older.status_code == 422 and "names no run" in older.json()["detail"]
    start = client.get(f"/api/runs/{run_b}/answers", params={"after": "0.0"}, headers=auth_b)
    assert [e["label_id"] for e in start.json()["events"]] == [1, 3]


def test_a_cursor_of_run_0_past_the_start_is_refused_rather_than_skipping_answers(
    client: TestClient,
) -> None:
    """'0.1.0' is no cursor the feed gives (run 0 is the start's alone): read as one, it
    skipped the answers up to label 1."""
    run_id, auth = external_run(client)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                json={"pairs": [pair("k1", a, b), pair("k2", b, a)]})
    token = bearer(new_labeller(client, "ivy"))
    for _ in range(2):
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
        assert answer(client, token, shown, "left").status_code == 201
    url = f"/api/runs/{run_id}/answers"
    for cursor in ("0.1.0", "0.0.1", "0.0.0"):
        read = client.get(url, params={"after": cursor}, headers=auth)
        assert read.status_code == 422, (cursor, read.text)
        detail = read.json()["detail"]
        assert f"cursor {cursor!r} names run 0" in detail and "'0.0'" in detail, detail
        assert "'<run>.<label>.<withdrawal>'" in detail, detail
    start = client.get(url, params={"after": "0.0"}, headers=auth).json()
    assert [e["label_id"] for e in start["events"]] == [1, 2]


def test_a_pair_pushed_by_mistake_is_withdrawn_and_shown_to_nobody_again(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client, budget=2)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    pushed = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                         json={"pairs": [pair("oops", a, b), pair("kept", b, a)]}).json()
    oops, kept = (item["query_id"] for item in pushed["pairs"])
    token = bearer(new_labeller(client, "ann"))
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
    assert shown["query_id"] == oops  # on ann's screen when its client withdraws it
    url = f"/api/runs/{run_id}/pairs/{oops}/withdraw"
    withdrawn = client.post(url, headers=auth)
    assert withdrawn.status_code == 200, withdrawn.text
    assert withdrawn.json() == {
        "query_id": oops, "key": "oops", "meta": None, "gold": False, "k": 1, "answers": [],
        "aggregate": None, "tie": False, "complete": False, "withdrawn": True}
    refused = answer(client, token, shown, "left")
    assert refused.status_code == 409 and "takes no more answers" in refused.json()["detail"]
    assert client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()["labels_used"] == 0
    # The next pair ann or anyone is shown is the one left, and then none.
    assert client.get(f"/api/label/next?run_id={run_id}&ahead_of={oops}",
                      headers=token).json()["query_id"] == kept
    other = bearer(new_labeller(client, "bob"))
    assert client.get(f"/api/label/next?run_id={run_id}", headers=other).status_code == 204
    feed = client.get(f"/api/runs/{run_id}/answers", headers=auth).json()
    assert (feed["events"], feed["open_pairs"]) == ([], 1)
    # Withdrawn again, it changes nothing; its answer is free for another pair of the budget.
    assert client.post(url, headers=auth).json() == withdrawn.json()
    more = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("oops", a, b), pair("new", a, a)]})
    assert more.status_code == 201, more.text
    assert [(p["key"], p["created"]) for p in more.json()["pairs"]] == [
        ("oops", False), ("new", True)]  # its key stays used, and comes back withdrawn
    states = client.get(f"/api/runs/{run_id}/pairs", params={"key": ["oops", "new"]},
                        headers=auth).json()["pairs"]
    assert [state["withdrawn"] for state in states] == [True, False]


def test_a_pair_with_an_answer_is_not_withdrawn(client: TestClient) -> None:
    run_id, auth = external_run(client, labels_per_query=3, practice_pairs=1)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    pushed = client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("practice", a, b, gold="first", returns=[2.0, 1.0]), pair("half", b, a),
        pair("taken-back", a, b)]})
    practice, half, taken_back = (item["query_id"] for item in pushed.json()["pairs"])
    token = bearer(new_labeller(client, "cat"))
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
    assert shown["query_id"] == practice and answer(client, token, shown, "left").status_code == 201
    for _ in ("half", "taken-back"):
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
        assert answer(client, token, shown, "left").status_code == 201
    assert shown["query_id"] == taken_back
    assert client.post(f"/api/label/{taken_back}/withdraw", headers=token,
                       json={}).status_code == 200
    url = f"/api/runs/{run_id}/pairs/{{}}/withdraw"
    # One answer of the three it asks for is enough: it stands, and the feed gave it.
    refused = client.post(url.format(half), headers=auth)
    assert refused.status_code == 409
    assert "has 1 answer(s) of the 3 it asks for" in refused.json()["detail"]
    refused = client.post(url.format(practice), headers=auth)
    assert refused.status_code == 409 and "practice pairs" in refused.json()["detail"]
    # An answer taken back stands no more: that pair has none.
    assert client.post(url.format(taken_back), headers=auth).json()["withdrawn"]
    assert client.post(url.format(taken_back + 1), headers=auth).status_code == 404
    other, other_auth = external_run(client)
    unknown = client.post(f"/api/runs/{other}/pairs/{half}/withdraw", headers=other_auth)
    assert unknown.status_code == 404 and f"run {other} has no pair" in unknown.text
    states = client.get(f"/api/runs/{run_id}/pairs", params={"key": ["half", "practice"]},
                        headers=auth).json()["pairs"]
    assert [(len(s["answers"]), s["withdrawn"]) for s in states] == [(1, False), (0, False)]


def test_a_gold_pair_known_by_its_answer_measures_labellers_and_costs_no_budget(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client, gold_rate=0.5)
    a, b = upload(client, run_id, auth, frames(1)), upload(client, run_id, auth, frames(2))
    # A gold pair comes no earlier than the ordinary pairs around it: pushed after one here.
    client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [
        pair("plain", b, a), pair("gold", a, b, gold="second")]})
    token = bearer(new_labeller(client, "eve"))
    for _ in range(2):  # eve answers "first" to both
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
        click = "left" if shown["left_is_first"] else "right"
        assert answer(client, token, shown, click).status_code == 201
    run = client.get(f"/api/runs/{run_id}", headers=OPERATOR).json()
    assert run["labels_used"] == 1  # the gold answer was free
    [eve] = client.get(f"/api/quality/labellers?run_id={run_id}", headers=OPERATOR).json()
    assert (eve["gold_accuracy"]["k"], eve["gold_accuracy"]["n"]) == (0, 1)
    events = client.get(f"/api/runs/{run_id}/answers", headers=auth).json()["events"]
    assert sorted((e["key"], e["gold"]) for e in events) == [("gold", True), ("plain", False)]


@pytest.mark.parametrize("fmt", ["webm"])
def test_an_uploaded_webm_is_served_as_webm(client: TestClient, tmp_path: Path,
                                            fmt: str) -> None:
    run_id, auth = external_run(client)
    path = tmp_path / f"clip.{fmt}"
    with imageio.get_writer(path, format="FFMPEG", fps=10, codec="libvpx",
                            macro_block_size=2) as writer:
        for frame in np.full((4, 32, 32, 3), 99, np.uint8):
            writer.append_data(frame)
    response = client.post(f"/api/runs/{run_id}/clips", content=path.read_bytes(),
                           headers=auth | {"content-type": "video/webm"})
    assert response.status_code == 201, response.text
    assert (response.json()["codec"], response.json()["frames"]) == ("vp8", 4)
    clip = response.json()["clip_id"]
    client.post(f"/api/runs/{run_id}/pairs", headers=auth, json={"pairs": [pair("w", clip, clip)]})
    token = bearer(new_labeller(client, "fay"))
    shown = client.get(f"/api/label/next?run_id={run_id}", headers=token).json()
    assert client.get(shown["left_clip_url"]).headers["content-type"] == "video/webm"


def test_an_operator_stops_an_external_run_at_once_and_can_run_it_again(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    a = upload(client, run_id, auth, frames(1))
    stopped = client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR)
    assert stopped.status_code == 200 and stopped.json()["status"] == "stopped"  # no worker
    refused = client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                          json={"pairs": [pair("k", a, a)]})
    assert refused.status_code == 409 and "takes no more pairs" in refused.json()["detail"]
    again = client.post(f"/api/runs/{run_id}/requeue", headers=OPERATOR)
    assert again.status_code == 200 and again.json()["status"] == "running"
    assert client.post(f"/api/runs/{run_id}/pairs", headers=auth,
                       json={"pairs": [pair("k", a, a)]}).status_code == 201
    activity = client.get(f"/api/runs/{run_id}/activity", headers=OPERATOR).json()
    assert activity["text"] == "waiting for 1 answer from 0 active labellers"


def test_an_operator_lists_a_runs_tokens_without_secrets_and_a_revoked_one_stops_at_once(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    spare = client.post(f"/api/runs/{run_id}/tokens", headers=OPERATOR).json()["token"]
    secret = auth["Authorization"].removeprefix("Bearer ")
    token_id = int(secret.split(".")[1])
    listed = client.get(f"/api/runs/{run_id}/tokens", headers=OPERATOR)
    assert listed.status_code == 200, listed.text
    assert [(t["id"], t["revoked_at"]) for t in listed.json()] == [
        (token_id, None), (int(spare.split(".")[1]), None)]
    assert secret.rsplit(".", 1)[1] not in listed.text and spare.rsplit(".", 1)[1] not in \
        listed.text
    url = f"/api/runs/{run_id}/answers"
    assert client.get(url, headers=auth).status_code == 200
    # Only an operator revokes, and a token only through its own run.
    revoke = f"/api/runs/{run_id}/tokens/{token_id}/revoke"
    assert client.post(revoke, headers=auth).status_code == 401
    assert client.get(f"/api/runs/{run_id}/tokens", headers=auth).status_code == 401
    labeller = bearer(new_labeller(client, "gus"))
    assert client.post(revoke, headers=labeller).status_code == 403
    other, _ = external_run(client)
    wrong = client.post(f"/api/runs/{other}/tokens/{token_id}/revoke", headers=OPERATOR)
    assert wrong.status_code == 404 and f"no token {token_id}" in wrong.json()["detail"]
    assert client.post(f"/api/runs/{run_id}/tokens/0/revoke", headers=OPERATOR).status_code \
        == 422
    revoked = client.post(revoke, headers=OPERATOR)
    assert revoked.status_code == 200 and revoked.json()["revoked_at"] is not None
    for call in (lambda: client.get(url, headers=auth),
                 lambda: client.post(f"/api/runs/{run_id}/clips", content=frames(1),
                                     headers=auth | NPY)):
        refused = call()
        assert refused.status_code == 401 and "revoked" in refused.json()["detail"]
    assert client.get(url, headers=bearer(spare)).status_code == 200  # the other still works
    again = client.post(revoke, headers=OPERATOR)
    assert again.json()["revoked_at"] == revoked.json()["revoked_at"]


def test_a_wait_for_answers_ends_with_a_401_when_its_token_is_revoked(
    client: TestClient,
) -> None:
    run_id, auth = external_run(client)
    token_id = int(auth["Authorization"].split(".")[1])
    results: list[Any] = []
    waiting = threading.Thread(target=lambda: results.append(
        client.get(f"/api/runs/{run_id}/answers?wait=20", headers=auth)))
    started = time.monotonic()
    waiting.start()
    time.sleep(0.3)
    assert client.post(f"/api/runs/{run_id}/tokens/{token_id}/revoke",
                       headers=OPERATOR).status_code == 200
    waiting.join(10)
    assert results and results[0].status_code == 401
    assert time.monotonic() - started < 5  # at its next look, not when the wait ends


def test_the_calibration_report_reads_an_external_runs_answers_by_the_returns_its_client_pushed(
    client: TestClient, tmp_path: Path
) -> None:
    run_id, auth = external_run(client, budget=40, labels_per_query=2, gold_rate=0.3)
    study = Study("http://testserver", auth["Authorization"].removeprefix("Bearer "), run_id,
                  client=client, progress=False)
    rng = np.random.default_rng(5)
    returns = {f"p{i}": (float(rng.uniform(50, 150)), float(rng.uniform(50, 150)))
               for i in range(12)}
    clips = [rng.integers(0, 255, (6, 32, 48, 3), dtype=np.uint8) for _ in range(4)]
    # A gold pair known by its answer only: the report leaves its answers out of its numbers,
    # as any gold pair's, and counts them.
    pushed = study.ask([Pair(clips[i % 4], clips[(i + 1) % 4], key=key, returns=pair_returns)
                        for i, (key, pair_returns) in enumerate(returns.items())]
                       + [Pair(clips[0], clips[2], key="gold", gold="first")])
    by_query = {query.query_id: returns.get(query.key) for query in pushed}

    def truthful(shown: dict[str, Any]) -> str:
        first, second = by_query[shown["query_id"]] or (1.0, 0.0)
        return "left" if (first > second) == shown["left_is_first"] else "right"

    for name, pick in (("truthful", truthful), ("lefty", lambda _shown: "left")):
        token = bearer(new_labeller(client, name))
        while (shown := client.get(f"/api/label/next?run_id={run_id}", headers=token)
               ).status_code == 200:
            assert answer(client, token, shown.json(), pick(shown.json())).status_code == 201
    response = client.get(f"/api/quality/calibration?run_id={run_id}", headers=OPERATOR)
    assert response.status_code == 200, response.text
    report = response.json()
    assert (report["runs"], report["rows"], report["without_truth"], report["gold_answers"]) \
        == ([run_id], 26, 0, 2)
    truth, lefty = report["labellers"]
    assert (truth["name"], truth["rates"]["answers"], truth["rates"]["correct"]) == (
        "truthful", 12, 12)
    assert truth["rates"]["match_ratio"] == 1.0 and truth["fit"]["eps"] is not None
    assert lefty["position"]["left_share"] == 1.0 and lefty["rates"]["answers"] == 12
    assert lefty["rates"]["correct"] + lefty["rates"]["wrong"] == 12
    [algo] = report["algos"]
    assert (algo["algo"], algo["queries"], algo["rates"]["answers"]) == ("external", 12, 24)
    # The same numbers as the report of the run's export, as for any run.
    exported = client.get(f"/api/export?format=csv&run_id={run_id}", headers=OPERATOR)
    assert exported.status_code == 200, exported.text
    path = tmp_path / "labels.csv"
    path.write_bytes(exported.content)
    from_file = calibration_report(read_export(str(path)))
    assert report["everyone"]["fit"]["eps"] == from_file.everyone.fit.eps
    assert report["labellers"][0]["rates"] == asdict(from_file.labellers[0].rates)
    png = client.get(f"/api/quality/calibration.png?run_id={run_id}", headers=OPERATOR)
    assert png.status_code == 200 and png.content.startswith(b"\x89PNG")

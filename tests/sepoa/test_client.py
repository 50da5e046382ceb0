"""`sepoa.client` against the app: pairs asked, answered on the label API and read back; a
retried push makes no second query; a client killed while waiting resumes from its cursor."""

from __future__ import annotations

import asyncio
import io
import sys
import time
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from labelqueue import Query, make_engine, session_factory
from sepoa.client import (
    AsyncStudy,
    Pair,
    Study,
    StudyError,
    push_call,
)
from sepoa.client import Query as Asked
from sepoa.client_pairs import PUSH_BYTES, push_batches
from server.app import create_app
from server.settings import Settings

sys.path.insert(0, str(Path(__file__).parents[1] / "server"))
from server_helpers import OPERATOR, OPERATOR_TOKEN, bearer, new_labeller  # noqa: E402

URL = "http://testserver"


@pytest.fixture
def app_client(tmp_path: Path) -> Iterator[TestClient]:
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'queue.db'}", data_dir=tmp_path,
                        operator_token=OPERATOR_TOKEN, secret_key="test-secret-key-0123456789")
    with TestClient(create_app(settings)) as client:
        yield client


def run_and_token(client: TestClient, **body: Any) -> tuple[int, str]:
    run = client.post("/api/runs/external", headers=OPERATOR,
                      json={"task": "gym:HalfCheetah-v5", "budget": 20} | body).json()
    token = client.post(f"/api/runs/{run['id']}/tokens", headers=OPERATOR).json()["token"]
    return run["id"], token


def clip(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 255, (4, 16, 16, 3), dtype=np.uint8)


def pairs(n: int) -> list[Pair]:
    return [Pair(clip(2 * i), clip(2 * i + 1), returns=(float(i), -1.0), meta={"i": i})
            for i in range(n)]


def label_all(client: TestClient, run_id: int, name: str,
              pick: str | Callable[[dict[str, Any]], str] = "left", most: int = 100) -> int:
    """A person answers up to `most` pairs of the run on the label API, clicking `pick` (a
    side, or a function of the pair shown that says which)."""
    token, answered = bearer(new_labeller(client, name)), 0
    while answered < most:
        shown = client.get(f"/api/label/next?run_id={run_id}", headers=token)
        if shown.status_code == 204:
            break
        click = pick if isinstance(pick, str) else pick(shown.json())
        body = {"choice": click, "left_is_first": shown.json()["left_is_first"],
                "shown_at": datetime.now(UTC).isoformat()}
        assert client.post(f"/api/label/{shown.json()['query_id']}", headers=token,
                           json=body).status_code == 201
        answered += 1
    return answered


def picking(answers: dict[int, str]) -> Callable[[dict[str, Any]], str]:
    """Clicks that give these answers (first or second) by query id, whichever side shows
    the first segment."""
    def click(shown: dict[str, Any]) -> str:
        first = answers[shown["query_id"]] == "first"
        return "left" if first == shown["left_is_first"] else "right"
    return click


def stored_queries(client: TestClient) -> int:
    engine = make_engine(client.app.state.settings.database_url)  # type: ignore[attr-defined]
    with session_factory(engine)() as session:
        count = session.scalar(select(func.count()).select_from(Query)) or 0
    engine.dispose()
    return count


class Flaky(httpx.BaseTransport):
    """The app's transport, failing as `fail(request, attempt)` says: "before" (a connection
    refused), "after" (the server did the work, the answer was lost) or a status code."""

    def __init__(self, inner: httpx.BaseTransport,
                 fail: Callable[[httpx.Request, int], str | int | None]):
        self.inner, self.fail, self.seen = inner, fail, 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.seen += 1
        how = self.fail(request, self.seen)
        if how == "before":
            raise httpx.ConnectError("connection refused", request=request)
        response = self.inner.handle_request(request)
        if how == "after":
            response.read()
            raise httpx.ReadError("connection reset", request=request)
        if isinstance(how, int):
            return httpx.Response(how, json={"detail": "overloaded"}, request=request)
        return response


def test_asked_pairs_come_back_with_the_answers_people_gave(app_client: TestClient) -> None:
    run_id, token = run_and_token(app_client, labels_per_query=2)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    queries = study.ask(pairs(3))
    assert [q.created for q in queries] == [True] * 3
    ids = [q.query_id for q in queries]
    ann = dict(zip(ids, ("first", "first", "second"), strict=True))
    bob = dict(zip(ids, ("first", "second", "second"), strict=True))
    assert label_all(app_client, run_id, "ann", picking(ann)) == 3
    assert label_all(app_client, run_id, "bob", picking(bob)) == 3
    answers = study.wait_for(queries, timeout=10)
    # Agreeing answers are the aggregate; a first against a second ties: can't tell.
    assert answers == dict(zip([q.key for q in queries], ("first", "cant_tell", "second"),
                               strict=True))
    events = study.answers()  # the feed gives each of the six answers too
    assert sorted((e.query_id, e.labeller, e.answer) for e in events) == sorted(
        [(i, "ann", a) for i, a in ann.items()] + [(i, "bob", a) for i, a in bob.items()])
    with pytest.raises(StudyError) as refused:
        study.ask([Pair(clip(1), np.zeros((4, 16, 32, 3), np.uint8))])
    assert refused.value.status == 422 and "differ in shape" in str(refused.value)


def test_many_pairs_are_pushed_in_pushes_the_server_takes(tmp_path: Path) -> None:
    """Pairs with their meta past what one push's body holds (64 KiB by default, 8 here) go
    in pushes that fit, in order: the client splits a push the server finds too large."""
    settings = Settings(database_url=f"sqlite:///{tmp_path / 'queue.db'}", data_dir=tmp_path,
                        operator_token=OPERATOR_TOKEN, secret_key="test-secret-key-0123456789",
                        body_limit_bytes=8 * 1024)
    with TestClient(create_app(settings)) as client:
        run_id, token = run_and_token(client, budget=1000)
        study = Study(URL, token, run_id, client=client, progress=False)
        queries = study.ask([Pair(clip(1), clip(2), returns=(float(i), 0.5),
                                  meta={"round": 0, "starts": [i, i + 1]}) for i in range(200)])
        assert len(queries) == 200 and all(q.created for q in queries)
        assert [q.query_id for q in queries] == sorted(q.query_id for q in queries)
        assert stored_queries(client) == 200
    bodies = [{"key": f"k{i}", "meta": {"pad": "x" * 500}} for i in range(600)]
    batches = push_batches(bodies)
    assert [body for batch in batches for body in batch] == bodies and len(batches) == 6
    assert all(len(push_call(batch).content or b"") <= PUSH_BYTES for batch in batches)
    assert [len(b) for b in push_batches([{"key": f"k{i}"} for i in range(600)])] == [500, 100]


def test_a_retried_push_makes_no_second_query(app_client: TestClient) -> None:
    run_id, token = run_and_token(app_client)
    tries: dict[str, int] = {}

    def fail(request: httpx.Request, _seen: int) -> str | int | None:
        path = request.url.path.rsplit("/", 1)[-1]
        tries[path] = tries.get(path, 0) + 1
        if path == "clips" and tries[path] == 1:
            return 503
        if path == "clips" and tries[path] == 2:
            return "before"
        return "after" if path == "pairs" and tries[path] == 1 else None

    app_client._transport = Flaky(app_client._transport, fail)
    study = Study(URL, token, run_id, client=app_client, progress=False, backoff=0.01)
    queries = study.ask(pairs(2))
    assert tries["pairs"] == 2  # the first push was stored, its answer lost, then retried
    assert [q.created for q in queries] == [False, False] and stored_queries(app_client) == 2
    assert [q.query_id for q in study.ask(pairs(2))] == [q.query_id for q in queries]
    assert stored_queries(app_client) == 2
    study.core.retries = 1
    app_client._transport = Flaky(app_client._transport, lambda _r, _n: 502)
    with pytest.raises(StudyError, match="gave up after 2 tries"):
        study.answers()


def test_a_pair_asked_twice_in_one_ask_is_one_query(app_client: TestClient) -> None:
    """As asked again in a later ask: the same content is the same key, and one push may
    not name a key twice (the server's 422 for it once failed the whole ask)."""
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    again, other = pairs(2)
    queries = study.ask([again, other, again])
    assert queries[0] == queries[2] and queries[0].key != queries[1].key
    assert stored_queries(app_client) == 2
    assert study.ask([other, other]) == [Asked(queries[1].key, queries[1].query_id, False)] * 2


def test_numpy_numbers_in_returns_and_meta_go_as_plain_ones(app_client: TestClient) -> None:
    """RL code's returns are often float32 sums and its ids int64: json.dumps refused them
    (TypeError). They go as the Python numbers they are, under the same key."""
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    [asked] = study.ask([Pair(clip(1), clip(2), returns=(np.float32(2.5), np.float64(-1.0)),
                              meta={"episode": np.int64(7), "starts": np.array([3, 9])})])
    [same] = study.ask([Pair(clip(1), clip(2), returns=(2.5, -1.0),
                             meta={"episode": 7, "starts": [3, 9]})])
    assert asked.created and same == Asked(asked.key, asked.query_id, False)
    assert study.states([asked.key])[asked.key].meta == {"episode": 7, "starts": [3, 9]}


def test_frames_are_uint8_and_an_npy_files_bytes_are_a_clip(app_client: TestClient) -> None:
    """Float frames were cast to uint8 unscaled, so frames in [0, 1] went as a black clip:
    they are a ValueError naming the fix. Integer frames within 0-255 are the uint8 clip; the
    bytes of an .npy file are the clip they hold (they were sent as an MP4, a 422)."""
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    frames = clip(1)
    with pytest.raises(ValueError, match=r"float32.*\(frames \* 255\)"):
        study.ask([Pair(frames / np.float32(255), clip(2))])
    with pytest.raises(ValueError, match="int16"):
        study.upload(frames.astype(np.int16) + 256)
    assert stored_queries(app_client) == 0
    uploaded = study.upload(frames)
    assert study.upload(frames.astype(np.int64)) == uploaded
    npy = io.BytesIO()
    np.save(npy, frames)
    assert study.upload(npy.getvalue()) == uploaded


def test_a_client_killed_while_waiting_resumes_from_its_cursor(
    app_client: TestClient, tmp_path: Path
) -> None:
    run_id, token = run_and_token(app_client)
    cursor = tmp_path / "run.cursor"
    first = Study(URL, token, run_id, client=app_client, progress=False, cursor_file=cursor)
    queries = first.ask(pairs(4))
    label_all(app_client, run_id, "cat", most=2)
    seen = [event.key for event in first.answers()]
    assert len(seen) == 2 and first.answers() == []  # read on: those two are handled
    assert cursor.read_text() == first.cursor
    label_all(app_client, run_id, "dan", most=1)
    [mid_page] = first.answers()
    del first  # killed while it handled that page: its cursor file is still before it
    label_all(app_client, run_id, "eve", most=1)
    again = Study(URL, token, run_id, client=app_client, progress=False, cursor_file=cursor)
    assert [q.created for q in again.ask(pairs(4))] == [False] * 4  # re-asked: no duplicate
    rest = again.answers()
    assert [e.label_id for e in rest][:1] == [mid_page.label_id]  # read again, not lost
    assert len(rest) == 2 and not {e.key for e in rest} & set(seen)
    assert set(seen) | {e.key for e in rest} == {q.key for q in queries}  # nothing lost
    assert stored_queries(app_client) == 4


def test_a_client_that_fails_while_handling_a_page_reads_it_again(
    app_client: TestClient, tmp_path: Path
) -> None:
    run_id, token = run_and_token(app_client)
    cursor = tmp_path / "run.cursor"
    with pytest.raises(RuntimeError), Study(URL, token, run_id, client=app_client,
                                            progress=False, cursor_file=cursor) as study:
        study.ask(pairs(1))
        label_all(app_client, run_id, "fay")
        assert len(study.answers()) == 1
        raise RuntimeError("the caller failed before it handled the page")
    assert not cursor.exists()
    with Study(URL, token, run_id, client=app_client, progress=False,
               cursor_file=cursor) as study:
        assert len(study.answers()) == 1  # the page again: handled this time
    assert cursor.read_text() == f"{run_id}.1.0"


def test_wait_for_returns_answers_read_before_a_crash_from_its_cursor_file(
    app_client: TestClient, tmp_path: Path
) -> None:
    run_id, token = run_and_token(app_client)
    cursor = tmp_path / "run.cursor"
    first = Study(URL, token, run_id, client=app_client, progress=False, cursor_file=cursor)
    queries = first.ask(pairs(2))
    label_all(app_client, run_id, "cat", most=1)
    with pytest.raises(TimeoutError, match="1 of 2 pairs"):
        first.wait_for(queries, timeout=0.5)
    del first  # killed here, with the first pair's answer read past in its cursor file
    label_all(app_client, run_id, "dan", most=1)
    again = Study(URL, token, run_id, client=app_client, progress=False, cursor_file=cursor)
    assert set(again.wait_for(again.ask(pairs(2)), timeout=5)) == {q.key for q in queries}


def test_a_client_waits_for_pairs_whose_answers_it_read_before(
    app_client: TestClient,
) -> None:
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    first, second = study.ask(pairs(1)), study.ask(pairs(2)[1:])
    label_all(app_client, run_id, "eve")
    assert len(study.answers()) == 2  # both answers read: the feed gives them no more
    assert set(study.wait_for(first, timeout=5)) == {first[0].key}
    assert set(study.wait_for(second, timeout=5)) == {second[0].key}
    with pytest.raises(ValueError, match="no pair of this run"):
        study.wait_for([Asked("nobody's", 1, False)], timeout=5)


def test_a_pair_whose_answers_are_all_skips_is_answered_skip(app_client: TestClient) -> None:
    """A skip counts toward k as the queue counts it (nobody is asked again): wait_for gives
    the pair back with the aggregate skip rather than wait for ever."""
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    queries = study.ask(pairs(2))
    label_all(app_client, run_id, "kim", "skip", most=1)
    label_all(app_client, run_id, "lee", "left", most=1)
    answers = study.wait_for(queries, timeout=5)
    assert sorted(answers.values()) == ["first", "skip"]


def test_wait_for_ends_when_the_run_is_stopped(app_client: TestClient) -> None:
    """A stopped run's feed waits for nothing: wait_for says the run is over at once rather
    than ask again and again until its time is up."""
    run_id, token = run_and_token(app_client)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    queries = study.ask(pairs(1))
    assert app_client.post(f"/api/runs/{run_id}/stop", headers=OPERATOR).status_code == 200
    started = time.monotonic()
    with pytest.raises(StudyError, match="the run is stopped: 1 of 1 pairs"):
        study.wait_for(queries, timeout=5)
    assert time.monotonic() - started < 2


def test_wait_for_refuses_a_gold_pair_at_once(app_client: TestClient) -> None:
    """A gold pair takes the answer of everyone it is shown to: never complete, so wait_for
    says so instead of waiting for ever; its answers come in answers()."""
    run_id, token = run_and_token(app_client, gold_rate=0.5)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    [gold] = study.ask([Pair(clip(1), clip(2), key="gold", gold="first")])
    label_all(app_client, run_id, "gil", "left")
    started = time.monotonic()
    with pytest.raises(ValueError, match=r"gold pairs .* \['gold'\]"):
        study.wait_for([gold], timeout=3)
    assert time.monotonic() - started < 2
    assert all(event.gold for event in study.answers())


def test_asyncio_waits_at_once_each_get_their_pairs(app_client: TestClient) -> None:
    run_id, token = run_and_token(app_client)

    async def main() -> list[dict[str, str]]:
        transport = httpx.ASGITransport(app=app_client.app)  # type: ignore[arg-type]
        async with httpx.AsyncClient(transport=transport, base_url=URL) as http, AsyncStudy(
                URL, token, run_id, progress=False, client=http) as study:
            asked = [await study.ask([pair]) for pair in pairs(3)]
            waits = [asyncio.create_task(study.wait_for(queries, timeout=20))
                     for queries in asked]
            await asyncio.sleep(0.2)  # each has read where its pair stands: unanswered
            await asyncio.to_thread(label_all, app_client, run_id, "fay")
            labelled = time.monotonic()
            answered = await asyncio.gather(*waits)
            return answered, time.monotonic() - labelled

    answered, after = asyncio.run(main())
    assert [len(answers) for answers in answered] == [1, 1, 1]
    # One read brings every pair's answer: the waits queued behind it read no more (each of
    # them used to wait out a long poll of its own for answers already noted).
    assert after < 10, f"the waits ended {after:.1f} s after the last answer"


def test_a_cursor_file_of_another_run_is_refused(app_client: TestClient,
                                                 tmp_path: Path) -> None:
    runs = [run_and_token(app_client) for _ in range(2)]
    cursor = tmp_path / "run.cursor"
    (first, first_token), (second, second_token) = runs
    study = Study(URL, first_token, first, client=app_client, progress=False, cursor_file=cursor)
    study.ask(pairs(1))
    label_all(app_client, first, "ida")
    assert len(study.answers()) == 1 and study.answers() == []
    assert cursor.read_text() == f"{first}.1.0"
    with pytest.raises(ValueError, match=f"run {first}'s cursor, not run {second}'s"):
        Study(URL, second_token, second, client=app_client, cursor_file=cursor)
    cursor.write_text("1.0")  # the older form, naming no run
    with pytest.raises(ValueError, match="names no run: delete the file"):
        Study(URL, first_token, first, client=app_client, cursor_file=cursor)


def test_the_asyncio_client_asks_and_reads_the_same(app_client: TestClient) -> None:
    run_id, token = run_and_token(app_client)

    async def main() -> tuple[list[Any], list[Any]]:
        transport = httpx.ASGITransport(app=app_client.app)  # type: ignore[arg-type]
        async with httpx.AsyncClient(transport=transport, base_url=URL) as http, AsyncStudy(
                URL, token, run_id, progress=False, client=http) as study:
            queries = await study.ask(pairs(2))
            await asyncio.to_thread(label_all, app_client, run_id, "eve")
            return queries, list((await study.wait_for(queries, timeout=10)).items())

    queries, answers = asyncio.run(main())
    assert [q.created for q in queries] == [True, True]
    assert {key for key, _ in answers} == {q.key for q in queries}


def test_a_withdrawn_pair_is_answered_by_nobody_and_waited_for_by_none(
    app_client: TestClient,
) -> None:
    run_id, token = run_and_token(app_client, budget=2)
    study = Study(URL, token, run_id, client=app_client, progress=False)
    oops, kept = study.ask(pairs(2))
    state = study.withdraw(oops)
    assert (state.key, state.withdrawn, state.answers) == (oops.key, True, {})
    assert study.withdraw(oops.query_id) == state  # again: nothing changes
    assert study.states([oops.key, kept.key])[kept.key].withdrawn is False
    with pytest.raises(ValueError, match=rf"withdrawn pairs .* \['{oops.key}'\]"):
        study.wait_for([oops, kept], timeout=3)
    # The withdrawn pair is shown to nobody: una answers the other one only.
    assert label_all(app_client, run_id, "una", picking({kept.query_id: "first"})) == 1
    assert study.wait_for([kept], timeout=5) == {kept.key: "first"}
    with pytest.raises(StudyError, match="has 1 answer") as refused:
        study.withdraw(kept)
    assert refused.value.status == 409
    for wrong in (0, oops.key, True):
        with pytest.raises(ValueError, match="a Query that ask gave, or its query_id"):
            study.withdraw(wrong)  # type: ignore[arg-type]
    # Its budget is free again: a third pair fits a budget of two.
    assert [q.created for q in study.ask(pairs(3))] == [False, False, True]


def test_a_wait_under_way_ends_when_its_pair_is_withdrawn(app_client: TestClient) -> None:
    run_id, token = run_and_token(app_client)

    async def main() -> None:
        transport = httpx.ASGITransport(app=app_client.app)  # type: ignore[arg-type]
        async with httpx.AsyncClient(transport=transport, base_url=URL) as http, AsyncStudy(
                URL, token, run_id, progress=False, client=http) as study:
            [asked] = await study.ask(pairs(1))
            # It reads where its pair stands, then long-polls the feed (5 s at most here).
            waiting = asyncio.create_task(study.wait_for([asked], timeout=5))
            await asyncio.sleep(0.2)
            assert (await study.withdraw(asked)).withdrawn
            with pytest.raises(StudyError, match=rf"withdrawn while waited for .*{asked.key}"):
                await waiting  # said once its poll ends: no TimeoutError

    asyncio.run(main())


class Uploads:
    """The app, counting the clip uploads it serves at once (the most in `peak`)."""

    def __init__(self, app: Any):
        self.app, self.now, self.peak = app, 0, 0

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if not (scope["type"] == "http" and scope["path"].endswith("/clips")):
            return await self.app(scope, receive, send)
        self.now += 1
        self.peak = max(self.peak, self.now)
        try:
            await self.app(scope, receive, send)
        finally:
            self.now -= 1


@pytest.mark.parametrize("bound", [None, 2])
def test_the_asyncio_client_uploads_a_few_clips_at_once(app_client: TestClient,
                                                        bound: int | None) -> None:
    """A batch of many pairs opens no connection per clip at once: at most 4 uploads (or
    `uploads`) are under way on the server at any time."""
    run_id, token = run_and_token(app_client, budget=100)
    server = Uploads(app_client.app)
    given = {} if bound is None else {"uploads": bound}

    async def main() -> list[Asked]:
        transport = httpx.ASGITransport(app=server)  # type: ignore[arg-type]
        async with httpx.AsyncClient(transport=transport, base_url=URL) as http, AsyncStudy(
                URL, token, run_id, progress=False, client=http, **given) as study:
            return await study.ask(pairs(3))

    asked = asyncio.run(main())
    assert len({query.query_id for query in asked}) == 3  # six clips, uploaded
    assert server.peak == (bound or 4)
    for wrong in (0, -1, True, 2.5, "4"):
        with pytest.raises(ValueError, match="uploads is the most clips uploading at once"):
            AsyncStudy(URL, token, run_id, uploads=wrong)  # type: ignore[arg-type]

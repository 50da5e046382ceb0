"""A Python client of an external run: ask people which of two clips is better, from any RL code.

    from sepoa.client import Pair, Study

    study = Study("http://127.0.0.1:8000", token, run=3, cursor_file="run3.cursor")
    queries = study.ask([Pair(frames_a, frames_b, returns=(12.5, 3.0), meta={"ids": [7, 9]})])
    answers = study.wait_for(queries)  # {key: "first" | "second" | "equal" | "cant_tell" | "skip"}

`token` is the run's token (`POST /api/runs/{id}/tokens`, an operator's call; an operator revokes it
with `POST /api/runs/{id}/tokens/{token_id}/revoke`, after which every call is a `StudyError` with
status 401). A clip is a frame array (uint8 (frames, height, width, 3), or integers within 0-255;
float frames are a ValueError: the server encodes it as the app's own clips are), an MP4, WebM or
.npy file, or such a file's bytes. Each pair's idempotency key is its own `key`, or one made from
its content: pushing the same pairs again (a retry, a client restarted after a crash), or one pair
twice in an `ask`, makes no second query. NumPy numbers in `returns` and `meta` go as plain ones.
Requests that fail on the way (a connection error, a 5xx, a 429) are retried with exponential
backoff; a 4xx is a `StudyError` naming the problem. The answers feed is read from a cursor, kept in
`cursor_file` when given, so a client killed while it waits reads on from where it was: nothing is
lost. The file moves past a page of answers when the next read begins (or at `close()`), so a client
killed while it handles a page reads that page again. The cursor names its run: another run's file
is a ValueError. `wait_for` reads where its pairs stand before it follows the feed, so it also
returns pairs whose answers the cursor has passed (read by `answers()`, by another wait, or before a
restart). A pair nobody has answered yet is withdrawn with `withdraw`. `AsyncStudy` is the same
over asyncio, with at most `uploads` clips uploading at once.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from urllib.parse import quote

import httpx
from tqdm import tqdm  # type: ignore[import-untyped]

from sepoa.client_pairs import Clip, Pair, clip_body, compact, each_once, pair_body, push_batches

LONGEST_WAIT_S = 60.0
"""the longest one answers request waits on the server"""
STATES_KEYS = 100
"""the most keys one read of pair states names (the server's limit)"""
STATES_URL_CHARS = 6000
"""the most characters of keys one read of pair states sends (a URL stays short)"""
UPLOADS = 4
"""the most clips `AsyncStudy.ask` uploads at once, by default"""


class StudyError(Exception):
    """The server refused a request (a 4xx), or kept failing it past the retries."""

    def __init__(self, status: int | None, detail: Any):
        super().__init__(f"{status}: {detail}" if status is not None else str(detail))
        self.status = status
        self.detail = detail


@dataclass(frozen=True)
class Query:
    """A pushed pair: its key, its query on the server, and whether this push stored it."""

    key: str
    query_id: int
    created: bool


@dataclass(frozen=True)
class AnswerEvent:
    """An answer to one of the run's pairs, or one taken back, with the pair as it stands."""

    kind: Literal["answer", "withdrawal"]
    key: str
    query_id: int
    label_id: int
    """the answer's id (a withdrawal's is the answer it takes back): with `kind`, it tells an
    event read twice (after a restart, see `Study.answers`) from a new one"""
    labeller: str
    answer: str
    aggregate: str | None
    """the majority of the pair's standing answers: first, second, equal, cant_tell (when
    most cannot tell or two answers tie), or skip (when every one is a skip); None with none
    standing"""
    tie: bool
    complete: bool
    """the pair has its k answers (skips count: nobody is asked again)"""
    gold: bool
    answers: dict[str, str]
    """each labeller's standing answer"""
    meta: Mapping[str, Any] | None
    raw: Mapping[str, Any] = field(repr=False)
    withdrawn: bool = False
    """the run's client withdrew the pair (`Study.withdraw`): it gets no more answers"""

    @classmethod
    def of(cls, event: Mapping[str, Any]) -> AnswerEvent:
        return cls(kind=event["kind"], key=event["key"], query_id=event["query_id"],
                   label_id=event["label_id"], labeller=event["labeller"], answer=event["answer"],
                   aggregate=event["aggregate"], tie=event["tie"], complete=event["complete"],
                   gold=event["gold"], meta=event["meta"], raw=event,
                   withdrawn=event.get("withdrawn", False),
                   answers={given["labeller"]: given["answer"] for given in event["answers"]})


@dataclass(frozen=True)
class PairState:
    """One of the run's pairs as it stands now (`Study.states`): its standing answers and
    their tally, as an `AnswerEvent` carries them."""

    key: str
    query_id: int
    aggregate: str | None
    tie: bool
    complete: bool
    gold: bool
    answers: dict[str, str]
    meta: Mapping[str, Any] | None
    withdrawn: bool = False
    """the run's client withdrew the pair (`Study.withdraw`): it gets no answer"""

    @classmethod
    def of(cls, state: Mapping[str, Any]) -> PairState:
        return cls(key=state["key"], query_id=state["query_id"], aggregate=state["aggregate"],
                   tie=state["tie"], complete=state["complete"], gold=state["gold"],
                   meta=state["meta"], withdrawn=state.get("withdrawn", False),
                   answers={given["labeller"]: given["answer"] for given in state["answers"]})


# What both forms share: requests as plain data, and what to make of the answers.

@dataclass(frozen=True)
class Call:
    method: str
    path: str
    params: Mapping[str, Any] | None = None
    json: Any = None
    content: bytes | None = None
    content_type: str | None = None
    timeout: float | None = None


def push_call(batch: Sequence[dict[str, Any]]) -> Call:
    return Call("POST", "/pairs", content=compact({"pairs": list(batch)}),
                content_type="application/json")


def withdraw_call(query: Query | int) -> Call:
    query_id = query.query_id if isinstance(query, Query) else query
    if isinstance(query_id, bool) or not isinstance(query_id, int) or query_id < 1:
        raise ValueError(f"withdraw takes a Query that ask gave, or its query_id (an int of "
                         f"at least 1); got {query!r}")
    return Call("POST", f"/pairs/{query_id}/withdraw")


def halves(batch: Sequence[dict[str, Any]], error: StudyError) -> list[Sequence[dict[str, Any]]]:
    """A push the server found too large (413), in two; the error again for any other
    refusal, or a single pair."""
    if error.status != 413 or len(batch) < 2:
        raise error
    return [batch[:len(batch) // 2], batch[len(batch) // 2:]]


def queries_of(pushed: Iterable[Mapping[str, Any]]) -> list[Query]:
    return [Query(item["key"], item["query_id"], item["created"]) for item in pushed]


def in_order(bodies: Sequence[Mapping[str, Any]], pushed: Sequence[Query]) -> list[Query]:
    """One query per pair asked, in order (a pair asked twice was pushed once: `each_once`)."""
    by_key = {query.key: query for query in pushed}
    return [by_key[body["key"]] for body in bodies]


def retry_after(response: httpx.Response | None, attempt: int, backoff: float) -> float | None:
    """Seconds to wait before trying again, or None when the request is not to be retried: a
    connection error (no response), a 5xx or a 429 is retried."""
    if response is not None and response.status_code < 500 and response.status_code != 429:
        return None
    header = None if response is None else response.headers.get("retry-after")
    if header is not None and header.replace(".", "", 1).isdigit():
        return float(header)
    return float(min(backoff * 2**attempt, 10.0))


def checked(response: httpx.Response) -> Any:
    if response.status_code >= 400:
        try:
            detail = response.json().get("detail")
        except ValueError:
            detail = response.text
        raise StudyError(response.status_code, detail)
    return response.json()


@dataclass(frozen=True)
class Done:
    value: Any


class _Core:
    """The state both forms keep: where the run is, its cursor, how to retry."""

    def __init__(self, url: str, token: str, run: int, *, retries: int, backoff: float,
                 cursor_file: str | os.PathLike[str] | None, progress: bool):
        self.url, self.run, self.retries, self.backoff = url.rstrip("/"), run, retries, backoff
        self.headers = {"Authorization": f"Bearer {token}"}
        self.cursor_file = None if cursor_file is None else Path(cursor_file)
        self.progress = progress
        self.waits: list[Waiting] = []
        """the waits under way: every read of the feed reaches each"""
        self.cursor = "0.0"
        if self.cursor_file is not None and self.cursor_file.exists():
            self.cursor = self.checked_cursor(self.cursor_file.read_text().strip() or "0.0")
        self.saved = self.cursor
        self.status: str | None = None
        """the run's status, as the last read of the feed gave it"""

    def checked_cursor(self, cursor: str) -> str:
        """A cursor file's cursor, if it is this run's (the feed's cursor names its run).
        ValueError for another run's, or one of two numbers (the older form, naming no run)."""
        parts = cursor.split(".")
        if cursor == "0.0" or (len(parts) == 3 and parts[0] == str(self.run)):
            return cursor
        where = f"cursor file {self.cursor_file} holds {cursor!r}"
        if len(parts) == 3:
            raise ValueError(f"{where}, run {parts[0]}'s cursor, not run {self.run}'s: give "
                             "each run a cursor file of its own")
        raise ValueError(f"{where}, a cursor that names no run: delete the file to read run "
                         f"{self.run}'s answers from the start")

    def keep(self, cursor: str) -> None:
        """Move the cursor on past a page just read; its file follows at the next read
        (`save`), once the caller has had the page."""
        self.cursor = cursor

    def save(self) -> None:
        """Write the cursor to its file (atomically), if a file keeps it: the pages read up to
        it are handled, since the caller reads on or closes."""
        if self.cursor_file is not None and self.saved != self.cursor:
            tmp = self.cursor_file.with_name(self.cursor_file.name + ".tmp")
            tmp.write_text(self.cursor)
            os.replace(tmp, self.cursor_file)
            self.saved = self.cursor

    def request(self, call: Call) -> dict[str, Any]:
        headers = dict(self.headers)
        if call.content_type is not None:
            headers["content-type"] = call.content_type
        return {"method": call.method, "url": f"{self.url}/api/runs/{self.run}{call.path}",
                "params": call.params, "json": call.json, "content": call.content,
                "headers": headers, "timeout": call.timeout}

    def outcome(self, response: httpx.Response | httpx.TransportError,
                attempt: int) -> Done | float:
        """What a try came to: the body (`Done`), seconds to wait before the next try, or a
        StudyError (a 4xx, or the last try failed)."""
        failed = response if isinstance(response, httpx.TransportError) else None
        answered = None if failed is not None else response
        assert answered is None or isinstance(answered, httpx.Response)
        wait = retry_after(answered, attempt, self.backoff)
        if wait is None:
            assert answered is not None
            return Done(checked(answered))
        if attempt >= self.retries:
            raise StudyError(None if answered is None else answered.status_code,
                             f"gave up after {self.retries + 1} tries: "
                             f"{failed if answered is None else answered.text}")
        return wait

    def answers_call(self, wait: float) -> Call:
        """The next read of the feed; the pages read before are handled, so the file moves on."""
        self.save()
        wait = max(0.0, min(wait, LONGEST_WAIT_S))
        return Call("GET", "/answers", params={"after": self.cursor, "wait": wait},
                    timeout=wait + 30.0)

    def read(self, body: Mapping[str, Any]) -> list[AnswerEvent]:
        """The events of a read of the feed, noted by every wait under way (a wait reads on
        from the one cursor the client keeps, so another's read may carry its pairs)."""
        events = [AnswerEvent.of(event) for event in body["events"]]
        self.keep(body["cursor"])
        self.status = body["status"]
        for waiting in self.waits:
            waiting.note(events)
        return events

    def withdrew(self, body: Mapping[str, Any]) -> PairState:
        """A pair this client withdrew, noted by every wait under way (none will answer it)."""
        state = PairState.of(body)
        for waiting in self.waits:
            waiting.note([state])
        return state

    @contextmanager
    def watching(self, waiting: Waiting) -> Iterator[None]:
        self.waits.append(waiting)
        try:
            yield
        finally:
            self.waits.remove(waiting)


def states_calls(keys: Sequence[str]) -> list[Call]:
    """Reads of pair states for these keys, each within the server's limit on keys and a
    URL of a sensible length."""
    calls: list[Call] = []
    batch: list[str] = []
    chars = 0
    for key in dict.fromkeys(keys):
        size = len(quote(key, safe="")) + 5
        if batch and (len(batch) == STATES_KEYS or chars + size > STATES_URL_CHARS):
            calls.append(Call("GET", "/pairs", params={"key": batch}))
            batch, chars = [], 0
        batch.append(key)
        chars += size
    if batch:
        calls.append(Call("GET", "/pairs", params={"key": batch}))
    return calls


def states_of(bodies: Iterable[Mapping[str, Any]]) -> dict[str, PairState]:
    return {state["key"]: PairState.of(state) for body in bodies for state in body["pairs"]}


class Waiting:
    """Asked pairs waited for: each one's aggregate once it has its k answers (a withdrawal
    can undo that), a tqdm bar of how many have, and the time left."""

    def __init__(self, queries: Sequence[Query], timeout: float | None, progress: bool):
        self.pending: dict[str, str | None] = {query.key: None for query in queries}
        self.withdrawn: dict[str, None] = {}
        """the pairs withdrawn while waited for, in the order it was noted"""
        self.deadline = None if timeout is None else time.monotonic() + timeout
        self.bar = tqdm(total=len(self.pending), desc="answered pairs", unit="pair",
                        disable=not progress)

    def done(self) -> int:
        return sum(value is not None for value in self.pending.values())

    def next_wait(self, status: str | None) -> float | None:
        """Seconds the next answers request may wait; None once every pair is answered.
        TimeoutError once the time is up; StudyError once the run is over (`status`, as the
        last read gave it: the feed waits for nothing then, and no answer is to come)."""
        if self.done() == len(self.pending):
            return None
        if self.withdrawn:
            raise StudyError(None, f"pairs withdrawn while waited for get no answer: "
                                   f"{list(self.withdrawn)[:5]}")
        if status is not None and status not in ("running", "paused"):
            raise StudyError(None, f"the run is {status}: {len(self.pending) - self.done()} of "
                                   f"{len(self.pending)} pairs still want answers")
        left = LONGEST_WAIT_S if self.deadline is None else self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"{len(self.pending) - self.done()} of {len(self.pending)} "
                               "pairs still want answers")
        return min(left, LONGEST_WAIT_S)

    def start(self, states: Mapping[str, PairState]) -> None:
        """Begin from where the pairs stand now (answers read before, by another wait or
        before a restart, come no more in the feed). ValueError for a key no pair of the run
        has, a withdrawn pair (it gets no answer), or a gold pair: it takes the answer of
        everyone it is shown to, so it is never complete; its answers come in `answers()`."""
        unknown = [key for key in self.pending if key not in states]
        if unknown:
            raise ValueError(f"no pair of this run has the key(s) {unknown[:5]}")
        gold = [key for key in self.pending if states[key].gold]
        if gold:
            raise ValueError(f"gold pairs are never complete, so wait_for does not wait for "
                             f"them (their answers come in answers()): {gold[:5]}")
        withdrawn = [key for key in self.pending if states[key].withdrawn]
        if withdrawn:
            raise ValueError(f"withdrawn pairs get no answer, so wait_for does not wait for "
                             f"them (ask again under a new key): {withdrawn[:5]}")
        self.note(states[key] for key in self.pending)

    def note(self, events: Iterable[AnswerEvent | PairState]) -> None:
        for event in events:
            if event.key in self.pending:
                self.pending[event.key] = event.aggregate if event.complete else None
                if event.withdrawn:
                    self.withdrawn[event.key] = None
        self.bar.n = self.done()
        self.bar.refresh()

    def result(self) -> dict[str, str]:
        return {key: str(value) for key, value in self.pending.items()}


class Study:
    """An external run, from its client's side (synchronous; `AsyncStudy` for asyncio)."""

    def __init__(self, url: str, token: str, run: int, *, retries: int = 6,
                 backoff: float = 0.5, cursor_file: str | os.PathLike[str] | None = None,
                 progress: bool = True, client: httpx.Client | None = None):
        self.core = _Core(url, token, run, retries=retries, backoff=backoff,
                          cursor_file=cursor_file, progress=progress)
        self.http = client or httpx.Client(timeout=60.0)
        self.owned = client is None
        """a client given is its giver's to close"""
        self.reading = threading.Lock()
        """one read of the feed at a time: its events reach the waits in the feed's order"""

    def close(self) -> None:
        """Keep the cursor past the last page read (it is handled), and close the connection
        (unless the httpx client was given)."""
        self.core.save()
        if self.owned:
            self.http.close()

    def __enter__(self) -> Study:
        return self

    def __exit__(self, failed: type[BaseException] | None, *_: object) -> None:
        if failed is None:
            self.close()
        elif self.owned:  # the last page may not be handled: it is read again next time
            self.http.close()

    @property
    def cursor(self) -> str:
        return self.core.cursor

    def call(self, call: Call) -> Any:
        """One request, retried on connection errors, 5xx and 429."""
        for attempt in range(self.core.retries + 1):
            try:
                outcome = self.core.outcome(self.http.request(**self.core.request(call)),
                                            attempt)
            except httpx.TransportError as error:
                outcome = self.core.outcome(error, attempt)
            if not isinstance(outcome, float):
                return outcome.value
            time.sleep(outcome)
        raise AssertionError("unreachable: the last attempt returns or raises")

    def upload(self, clip: Clip) -> str:
        """Upload one clip (the same bytes again are the same clip); its id."""
        content, kind = clip_body(clip)
        body = self.call(Call("POST", "/clips", content=content, content_type=kind))
        return str(body["clip_id"])

    def ask(self, pairs: Sequence[Pair]) -> list[Query]:
        """Push the pairs for people to compare; their queries, in order. They go in pushes
        that fit the server's limits (`push_batches`), each stored whole or not at all:
        should one fail, asking again makes no second query of a pair stored before. A pair
        given twice is pushed once, and both get its query."""
        bodies = [pair_body(pair, self.upload(pair.first), self.upload(pair.second))
                  for pair in pairs]
        pushed = [query for batch in push_batches(each_once(bodies)) for query in self.push(batch)]
        return in_order(bodies, pushed)

    def push(self, batch: Sequence[dict[str, Any]]) -> list[Query]:
        """One push of pairs' bodies (`pair_body`), in two when the server finds it too
        large."""
        try:
            return queries_of(self.call(push_call(batch))["pairs"])
        except StudyError as error:
            return [query for half in halves(batch, error) for query in self.push(half)]

    def withdraw(self, query: Query | int) -> PairState:
        """Withdraw a pair nobody has answered yet (pushed by mistake), by its `Query` or
        query_id: no labeller is shown it again, one who has it on screen cannot answer it, and
        the answers it asked of the budget are free again; its key stays used. The pair as it
        stands, `withdrawn`; withdrawing it again changes nothing, and a `wait_for` under way
        for it raises a StudyError. StudyError 409 for a pair with an answer (one of its k is
        enough) or one of the run's practice pairs, 404 for no pair of the run."""
        return self.core.withdrew(self.call(withdraw_call(query)))

    def answers(self, wait: float = 0.0) -> list[AnswerEvent]:
        """The answers and withdrawals since the cursor (waiting up to `wait` s, 60 at most,
        for one), and the cursor moved past them. The cursor file moves past a page when the
        next read begins, or at `close()`: a client killed while it handles a page reads that
        page again (each event at least once; its `label_id` and kind tell one apart)."""
        with self.reading:
            return self.core.read(self.call(self.core.answers_call(wait)))

    def states(self, keys: Sequence[str]) -> dict[str, PairState]:
        """Where the pairs under these keys stand now, by key (a key no pair of the run has
        is left out); it moves no cursor."""
        return states_of(self.call(call) for call in states_calls(keys))

    def wait_for(self, queries: Sequence[Query], timeout: float | None = None) -> dict[str, str]:
        """Wait until each query (an ordinary pair) has its k answers, from where the pairs
        stand now and then as the answers come (a tqdm bar counts them); the aggregate answer
        of each, by key. TimeoutError past `timeout` seconds; ValueError for a gold pair or a
        key no pair of the run has; StudyError once the run is stopped, finished or failed."""
        waiting = Waiting(queries, timeout, self.core.progress)
        with self.core.watching(waiting), waiting.bar:
            waiting.start(self.states(list(waiting.pending)))
            while True:  # decided under the read lock: another wait's read may have ended it
                with self.reading:
                    if (wait := waiting.next_wait(self.core.status)) is None:
                        break
                    self.core.read(self.call(self.core.answers_call(wait)))
        return waiting.result()


class AsyncStudy:
    """`Study` over asyncio (httpx's AsyncClient): the same calls, awaited. `ask` uploads at
    most `uploads` clips at once (4 by default): a batch of hundreds of pairs opens no hundreds
    of connections, nor asks the server to encode hundreds of clips at once."""

    def __init__(self, url: str, token: str, run: int, *, retries: int = 6,
                 backoff: float = 0.5, cursor_file: str | os.PathLike[str] | None = None,
                 progress: bool = True, client: httpx.AsyncClient | None = None,
                 uploads: int = UPLOADS):
        if isinstance(uploads, bool) or not isinstance(uploads, int) or uploads < 1:
            raise ValueError(f"uploads is the most clips uploading at once, an int of at "
                             f"least 1; got {uploads!r}")
        self.uploading = asyncio.Semaphore(uploads)
        self.core = _Core(url, token, run, retries=retries, backoff=backoff,
                          cursor_file=cursor_file, progress=progress)
        self.http = client or httpx.AsyncClient(timeout=60.0)
        self.owned = client is None
        self.reading = asyncio.Lock()

    async def aclose(self) -> None:
        self.core.save()
        if self.owned:
            await self.http.aclose()

    async def __aenter__(self) -> AsyncStudy:
        return self

    async def __aexit__(self, failed: type[BaseException] | None, *_: object) -> None:
        if failed is None:
            await self.aclose()
        elif self.owned:
            await self.http.aclose()

    @property
    def cursor(self) -> str:
        return self.core.cursor

    async def call(self, call: Call) -> Any:
        """One request, retried on connection errors, 5xx and 429."""
        for attempt in range(self.core.retries + 1):
            try:
                outcome = self.core.outcome(
                    await self.http.request(**self.core.request(call)), attempt)
            except httpx.TransportError as error:
                outcome = self.core.outcome(error, attempt)
            if not isinstance(outcome, float):
                return outcome.value
            await asyncio.sleep(outcome)
        raise AssertionError("unreachable: the last attempt returns or raises")

    async def upload(self, clip: Clip) -> str:
        async with self.uploading:
            content, kind = clip_body(clip)
            body = await self.call(Call("POST", "/clips", content=content, content_type=kind))
        return str(body["clip_id"])

    async def ask(self, pairs: Sequence[Pair]) -> list[Query]:
        ids = await asyncio.gather(*(self.upload(clip) for pair in pairs
                                     for clip in (pair.first, pair.second)))
        bodies = [pair_body(pair, ids[2 * i], ids[2 * i + 1]) for i, pair in enumerate(pairs)]
        return in_order(bodies, [query for batch in push_batches(each_once(bodies))
                                 for query in await self.push(batch)])

    async def push(self, batch: Sequence[dict[str, Any]]) -> list[Query]:
        try:
            return queries_of((await self.call(push_call(batch)))["pairs"])
        except StudyError as error:
            return [query for half in halves(batch, error) for query in await self.push(half)]

    async def withdraw(self, query: Query | int) -> PairState:
        """`Study.withdraw`, awaited."""
        return self.core.withdrew(await self.call(withdraw_call(query)))

    async def answers(self, wait: float = 0.0) -> list[AnswerEvent]:
        async with self.reading:
            return self.core.read(await self.call(self.core.answers_call(wait)))

    async def states(self, keys: Sequence[str]) -> dict[str, PairState]:
        return states_of([await self.call(call) for call in states_calls(keys)])

    async def wait_for(self, queries: Sequence[Query],
                       timeout: float | None = None) -> dict[str, str]:
        """`Study.wait_for`, awaited; several may wait at once."""
        waiting = Waiting(queries, timeout, self.core.progress)
        with self.core.watching(waiting), waiting.bar:
            waiting.start(await self.states(list(waiting.pending)))
            while True:  # decided under the read lock, as `Study.wait_for` does
                async with self.reading:
                    if (wait := waiting.next_wait(self.core.status)) is None:
                        break
                    self.core.read(await self.call(self.core.answers_call(wait)))
        return waiting.result()

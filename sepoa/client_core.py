"""What `sepoa.client`'s `Study` and `AsyncStudy` share: the records a run's client is given
(`Query`, `AnswerEvent`, `PairState`, `StudyError`), requests as plain data (`Call`) with the
retries and the reading of their answers (`Core`), the answers feed's cursor, and the waits for
asked pairs (`Waiting`). Nothing here sends a request: each form sends `Call`s its own way, in
a thread or awaited.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal
from urllib.parse import quote

import httpx
from tqdm import tqdm  # type: ignore[import-untyped]

from sepoa.client_pairs import compact

LONGEST_WAIT_S = 60.0
"""the longest one answers request waits on the server"""
STATES_KEYS = 100
"""the most keys one read of pair states names (the server's limit)"""
STATES_URL_CHARS = 6000
"""the most characters of keys one read of pair states sends (a URL stays short)"""


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


# Requests as plain data, and what to make of the answers.

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


class Core:
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

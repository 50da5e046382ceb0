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
from collections.abc import Sequence
from typing import Any

import httpx

from sepoa.client_core import (
    AnswerEvent,
    Call,
    Core,
    PairState,
    Query,
    StudyError,
    Waiting,
    halves,
    in_order,
    push_call,
    queries_of,
    states_calls,
    states_of,
    withdraw_call,
)
from sepoa.client_pairs import Clip, Pair, clip_body, each_once, pair_body, push_batches

__all__ = ["AnswerEvent", "AsyncStudy", "Clip", "Pair", "PairState", "Query", "Study",
           "StudyError", "push_call"]

UPLOADS = 4
"""the most clips `AsyncStudy.ask` uploads at once, by default"""


class Study:
    """An external run, from its client's side (synchronous; `AsyncStudy` for asyncio)."""

    def __init__(self, url: str, token: str, run: int, *, retries: int = 6,
                 backoff: float = 0.5, cursor_file: str | os.PathLike[str] | None = None,
                 progress: bool = True, client: httpx.Client | None = None):
        self.core = Core(url, token, run, retries=retries, backoff=backoff,
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
        self.core = Core(url, token, run, retries=retries, backoff=backoff,
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

"""Request dependencies: settings, a database session, and who is calling.

Auth is `Authorization: Bearer <token>`: a labeller's token (`labelqueue.authenticate`), or the
settings' `operator_token`, which acts as an operator that is not a labeller (it can manage runs
and labellers, not answer queries). Missing or unknown token: 401; wrong role: 403.

Every dependency here is `async def` and does no blocking work on the event loop: FastAPI runs
each plain `def` dependency in a thread of its own pool, a hand-off that cost more than the
dependency itself. So a request makes one trip to the pool, for its route, and a second only
when its token is not in the cache (the database check runs there).
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import threading
import time
from collections.abc import AsyncIterator, Callable
from concurrent.futures import Executor
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial
from typing import Annotated, Any, TypeVar

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from labelqueue import Role, WriterBusy, authenticate, without_waiting
from labelqueue.labellers import hash_token
from server.settings import Settings

T = TypeVar("T")


async def get_app_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


@asynccontextmanager
async def request_session(request: Request) -> AsyncIterator[Session]:
    """A session for one request; queue operations commit their own transactions.

    Made and closed on the event loop: making one touches no database, and closing one whose
    operations have all committed only drops it (a route's thread did the blocking work)."""
    sessions: sessionmaker[Session] = request.app.state.sessions
    session = sessions()
    try:
        yield session
    finally:
        if session.in_transaction():  # a route that left work open: end it off the loop
            await run_in_threadpool(session.close)
        else:
            session.close()


async def get_session(request: Request) -> AsyncIterator[Session]:
    async with request_session(request) as session:
        yield session


SettingsDep = Annotated[Settings, Depends(get_app_settings)]
SessionDep = Annotated[Session, Depends(get_session)]


@dataclass(frozen=True)
class Caller:
    """Who made the request: a labeller (with an id) or the settings' operator token (none)."""

    role: Role
    labeller_id: int | None
    name: str


HEADERS = {"WWW-Authenticate": "Bearer"}
BEARER = HTTPBearer(
    scheme_name="bearer",
    description="a labeller's token (`POST /api/labellers`) or the operator token from settings",
    auto_error=False,  # the 401s below name what is missing
)


def bearer_token(request: Request) -> str | None:
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


class TokenCache:
    """Labeller-role tokens checked in the last `seconds`, by their sha256: a labeller's every
    request would otherwise read its own row, on a thread of the pool, before doing its work.

    An operator-role labeller is never kept: its rights (make operators, restore labellers)
    must end the moment it is revoked, and operator traffic is too small to need a cache."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self._entries: dict[str, tuple[float, Caller]] = {}
        self._lock = threading.Lock()
        self._generation = 0  # bumped by `forget`; a check read before it must not be kept

    def get(self, token: str) -> Caller | None:
        key = hashlib.sha256(token.encode()).hexdigest()
        with self._lock:
            entry = self._entries.get(key)
        return entry[1] if entry is not None and entry[0] > time.monotonic() else None

    def generation(self) -> int:
        """Take this before reading a token's row, and give it to `put`."""
        with self._lock:
            return self._generation

    def forget(self, labeller_id: int) -> None:
        """Drop the labeller's entries: a change to it applies at once in this process (other
        server processes keep their entries until they run out, `seconds` at most)."""
        with self._lock:
            self._generation += 1
            self._entries = {
                k: v for k, v in self._entries.items() if v[1].labeller_id != labeller_id
            }

    def put(self, token: str, caller: Caller, *, generation: int) -> None:
        """Keep a check read at `generation`, unless a `forget` came since (the row read may
        predate the change) or the caller is an operator."""
        if self.seconds <= 0 or caller.role is Role.OPERATOR:
            return
        key = hashlib.sha256(token.encode()).hexdigest()
        now = time.monotonic()
        with self._lock:
            if generation != self._generation:
                return
            if len(self._entries) > 10_000:  # drop what has run out; bounded memory
                self._entries = {k: v for k, v in self._entries.items() if v[0] > now}
            self._entries[key] = (now + self.seconds, caller)


def known_caller(
    *, settings: Settings, token: str | None, cache: TokenCache | None = None
) -> Caller | None:
    """The caller a token names without asking the database (the operator token, or a
    labeller-role token in the cache); None when the database must say. 401 without a token."""
    if token is None:
        raise HTTPException(401, "missing bearer token (Authorization: Bearer <token>)", HEADERS)
    admin = settings.operator_token
    if admin is not None and hmac.compare_digest(token.encode(), admin.encode()):
        return Caller(role=Role.OPERATOR, labeller_id=None, name="operator-token")
    return cache.get(token) if cache is not None else None


def checked_caller(*, session: Session, token: str, cache: TokenCache | None = None) -> Caller:
    """The labeller a token names, from the database (blocking); 401 when it names none."""
    generation = cache.generation() if cache is not None else 0
    labeller = authenticate(session, token=token)
    if labeller is None:
        raise HTTPException(401, "invalid or revoked bearer token", HEADERS)
    caller = Caller(role=labeller.role, labeller_id=labeller.id, name=labeller.name)
    if cache is not None:
        cache.put(token, caller, generation=generation)
    return caller


def caller_from_token(
    *, session: Session, settings: Settings, token: str | None, cache: TokenCache | None = None
) -> Caller:
    """The caller a bearer token names (blocking); 401 when there is none or it is not valid."""
    caller = known_caller(settings=settings, token=token, cache=cache)
    if caller is not None:
        return caller
    assert token is not None
    return checked_caller(session=session, token=token, cache=cache)


async def request_caller(request: Request, session: Session, settings: Settings) -> Caller:
    """The caller of a request; 401 without a valid token. The database is asked (on a thread
    of the pool) only when the token is neither the operator's nor in the cache."""
    cache = get_token_cache(request)
    token = bearer_token(request)
    caller = known_caller(settings=settings, token=token, cache=cache)
    if caller is not None:
        return caller
    assert token is not None
    return await run_in_threadpool(checked_caller, session=session, token=token, cache=cache)


async def get_caller(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    _declared: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)],
) -> Caller:
    """The caller (the `bearer` security scheme in OpenAPI); 401 without a valid token."""
    return await request_caller(request, session, settings)


def must_be_operator(caller: Caller) -> Caller:
    if caller.role is not Role.OPERATOR:
        raise HTTPException(403, f"labeller {caller.name!r} is not an operator")
    return caller


def must_be_labeller(caller: Caller) -> Caller:
    if caller.labeller_id is None:
        raise HTTPException(403, "the operator token is not a labeller; create a labeller first")
    return caller


async def get_operator(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    return must_be_operator(caller)


async def get_labeller(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    return must_be_labeller(caller)


class LabelThreads:
    """The executor of the label API's queue work, and how many requests wait on it.

    The count keeps the requests in order: a request does its work on the event loop only when
    none is waiting for the executor, so it never overtakes one queued there. Token checks go
    through `serve` as well: sent to AnyIO's threads, they lengthened the closed-loop tail."""

    def __init__(self, executor: Executor):
        self.executor = executor
        self.waiting = 0  # changed on the event loop only

    async def run(self, work: Callable[[], T]) -> T:
        self.waiting += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self.executor, work)
        finally:
            self.waiting -= 1

    async def serve(self, work: Callable[[], T], *, inline: bool) -> T:
        """`work()`, on the event loop itself when `inline`, no request waits for the executor
        and SQLite's write lock is free at once (a read takes no lock); else on the executor.
        When another writer holds the lock, nothing has run yet (`WriterBusy` comes at the
        transaction's start), and the executor's thread waits for it instead of the loop."""
        if inline and self.waiting == 0:
            try:
                with without_waiting():
                    return work()
            except WriterBusy:
                pass
        return await self.run(work)


async def label_work(threads: LabelThreads | None, work: Callable[[], T], *, inline: bool) -> T:
    """`work()` where the label API's queue work runs (`LabelThreads.serve`); on AnyIO's
    threads in an app whose lifespan did not run (no label threads)."""
    if threads is None:
        return await run_in_threadpool(work)
    return await threads.serve(work, inline=inline)


@dataclass(frozen=True)
class LabellerCall:
    """A labeller's request as the label API's hot path takes it: the settings, the session
    factory and the labeller, from one plain `async` dependency (FastAPI's work per dependency,
    and more so per generator dependency, cost more than the dependencies themselves), and
    `serve` for its blocking work."""

    settings: Settings
    sessions: sessionmaker[Session]
    labeller_id: int
    threads: LabelThreads | None
    inline: bool = False
    """try the work on the event loop first (`Settings.label_work_inline`)"""
    token_hash: str | None = None
    """the hash of the bearer token the request came with: the queue work checks it is still
    the labeller's, in its own transaction, so a new token stops the old one at once whatever
    the token cache holds (`labelqueue.StaleToken`)"""

    def _in_session(self, service: Callable[..., T], kwargs: dict[str, Any]) -> T:
        with self.sessions() as session:
            return service(session, settings=self.settings, labeller_id=self.labeller_id,
                           token_hash=self.token_hash, **kwargs)

    async def serve(self, service: Callable[..., T], /, **kwargs: Any) -> T:
        """`service(session, settings=..., labeller_id=..., token_hash=..., **kwargs)` in a
        session of its own on the app's executor for queue work, awaited.

        A plain executor hand-off, not FastAPI's for a `def` route (AnyIO's worker threads,
        capacity limiter and cancel scopes cost more). On SQLite the executor has one thread
        (`Settings.label_threads`), and with `inline` the work runs on the event loop itself
        when it can (`LabelThreads.serve`): it is shorter than the hand-off."""
        work = partial(self._in_session, service, kwargs)
        return await label_work(self.threads, work, inline=self.inline)


def _checked_in_session(
    sessions: sessionmaker[Session], token: str, cache: TokenCache | None
) -> Caller:
    with sessions() as session:
        return checked_caller(session=session, token=token, cache=cache)


async def get_labeller_call(request: Request) -> LabellerCall:
    """`LabellerDep`, `SessionDep` and `SettingsDep` at once; 401/403 as `LabellerDep`. The
    routes that take it declare the `bearer` scheme in OpenAPI (`BEARER_SECURITY`)."""
    state = request.app.state
    settings: Settings = state.settings
    sessions: sessionmaker[Session] = state.sessions
    cache = get_token_cache(request)
    token = bearer_token(request)
    caller = known_caller(settings=settings, token=token, cache=cache)
    threads: LabelThreads | None = getattr(state, "label_threads", None)
    inline = settings.label_work_inline
    if caller is None:
        # A token not in the cache (every labeller's, each time its entry runs out) is read
        # where the queue work runs: on AnyIO's threads, behind a busy event loop, these reads
        # made the label API's slowest requests (benchmarks/README.md).
        assert token is not None
        check = partial(_checked_in_session, sessions, token, cache)
        caller = await label_work(threads, check, inline=inline)
    must_be_labeller(caller)
    assert caller.labeller_id is not None
    return LabellerCall(settings, sessions, caller.labeller_id, threads, inline,
                        None if token is None else hash_token(token))


BEARER_SECURITY: dict[str, Any] = {"security": [{"bearer": []}]}
"""`openapi_extra` of a route whose dependency checks the bearer token without `BEARER`"""


def get_token_cache(request: Request) -> TokenCache | None:
    cache: TokenCache | None = getattr(request.app.state, "token_cache", None)
    return cache


async def token_cache_dep(request: Request) -> TokenCache | None:
    return get_token_cache(request)


TokenCacheDep = Annotated[TokenCache | None, Depends(token_cache_dep)]
OperatorDep = Annotated[Caller, Depends(get_operator)]
LabellerDep = Annotated[Caller, Depends(get_labeller)]
LabellerCallDep = Annotated[LabellerCall, Depends(get_labeller_call)]

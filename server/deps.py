"""Request dependencies: settings, a database session, and who is calling.

Auth is `Authorization: Bearer <token>`: a labeller's token (`labelqueue.authenticate`), or the
settings' `operator_token`, which acts as an operator that is not a labeller (it can manage runs
and labellers, not answer queries). Missing or unknown token: 401; wrong role: 403.
"""

from __future__ import annotations

import hashlib
import hmac
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import Role, authenticate
from server.settings import Settings


def get_app_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def get_session(request: Request) -> Iterator[Session]:
    """A session for one request; queue operations commit their own transactions."""
    sessions: sessionmaker[Session] = request.app.state.sessions
    with sessions() as session:
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
    """Tokens checked in the last `seconds`, by their sha256: a labeller's every request would
    otherwise take the database's write lock (SQLite) just to read its own row."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self._entries: dict[str, tuple[float, Caller]] = {}
        self._lock = threading.Lock()

    def get(self, token: str) -> Caller | None:
        key = hashlib.sha256(token.encode()).hexdigest()
        with self._lock:
            entry = self._entries.get(key)
        return entry[1] if entry is not None and entry[0] > time.monotonic() else None

    def forget(self, labeller_id: int) -> None:
        """Drop the labeller's entries: a change to it applies at once in this process (other
        server processes keep their entries until they run out, `seconds` at most)."""
        with self._lock:
            self._entries = {
                k: v for k, v in self._entries.items() if v[1].labeller_id != labeller_id
            }

    def put(self, token: str, caller: Caller) -> None:
        if self.seconds <= 0:
            return
        key = hashlib.sha256(token.encode()).hexdigest()
        now = time.monotonic()
        with self._lock:
            if len(self._entries) > 10_000:  # drop what has run out; bounded memory
                self._entries = {k: v for k, v in self._entries.items() if v[0] > now}
            self._entries[key] = (now + self.seconds, caller)


def caller_from_token(
    *, session: Session, settings: Settings, token: str | None, cache: TokenCache | None = None
) -> Caller:
    """The caller a bearer token names; 401 when there is none or it is not valid."""
    if token is None:
        raise HTTPException(401, "missing bearer token (Authorization: Bearer <token>)", HEADERS)
    admin = settings.operator_token
    if admin is not None and hmac.compare_digest(token.encode(), admin.encode()):
        return Caller(role=Role.OPERATOR, labeller_id=None, name="operator-token")
    cached = cache.get(token) if cache is not None else None
    if cached is not None:
        return cached
    labeller = authenticate(session, token=token)
    if labeller is None:
        raise HTTPException(401, "invalid or revoked bearer token", HEADERS)
    caller = Caller(role=labeller.role, labeller_id=labeller.id, name=labeller.name)
    if cache is not None:
        cache.put(token, caller)
    return caller


def get_caller(
    request: Request,
    session: SessionDep,
    settings: SettingsDep,
    _declared: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)],
) -> Caller:
    """The caller (the `bearer` security scheme in OpenAPI); 401 without a valid token."""
    cache = get_token_cache(request)
    return caller_from_token(
        session=session, settings=settings, token=bearer_token(request), cache=cache
    )


def get_operator(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    if caller.role is not Role.OPERATOR:
        raise HTTPException(403, f"labeller {caller.name!r} is not an operator")
    return caller


def get_labeller(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    if caller.labeller_id is None:
        raise HTTPException(403, "the operator token is not a labeller; create a labeller first")
    return caller


def get_token_cache(request: Request) -> TokenCache | None:
    cache: TokenCache | None = getattr(request.app.state, "token_cache", None)
    return cache


TokenCacheDep = Annotated[TokenCache | None, Depends(get_token_cache)]
CallerDep = Annotated[Caller, Depends(get_caller)]
OperatorDep = Annotated[Caller, Depends(get_operator)]
LabellerDep = Annotated[Caller, Depends(get_labeller)]

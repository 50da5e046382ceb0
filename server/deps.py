"""Request dependencies: settings, a database session, and who is calling.

Auth is `Authorization: Bearer <token>`: a labeller's token (`labelqueue.authenticate`), or the
settings' `operator_token`, which acts as an operator that is not a labeller (it can manage runs
and labellers, not answer queries). Missing or unknown token: 401; wrong role: 403.
"""

from __future__ import annotations

import hmac
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
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


def bearer_token(request: Request) -> str | None:
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


def caller_from_token(*, session: Session, settings: Settings, token: str | None) -> Caller:
    """The caller a bearer token names; 401 when there is none or it is not valid."""
    if token is None:
        raise HTTPException(401, "missing bearer token (Authorization: Bearer <token>)", HEADERS)
    admin = settings.operator_token
    if admin is not None and hmac.compare_digest(token.encode(), admin.encode()):
        return Caller(role=Role.OPERATOR, labeller_id=None, name="operator-token")
    labeller = authenticate(session, token=token)
    if labeller is None:
        raise HTTPException(401, "invalid or revoked bearer token", HEADERS)
    return Caller(role=labeller.role, labeller_id=labeller.id, name=labeller.name)


def get_caller(request: Request, session: SessionDep, settings: SettingsDep) -> Caller:
    return caller_from_token(session=session, settings=settings, token=bearer_token(request))


def get_operator(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    if caller.role is not Role.OPERATOR:
        raise HTTPException(403, f"labeller {caller.name!r} is not an operator")
    return caller


def get_labeller(caller: Annotated[Caller, Depends(get_caller)]) -> Caller:
    if caller.labeller_id is None:
        raise HTTPException(403, "the operator token is not a labeller; create a labeller first")
    return caller


CallerDep = Annotated[Caller, Depends(get_caller)]
OperatorDep = Annotated[Caller, Depends(get_operator)]
LabellerDep = Annotated[Caller, Depends(get_labeller)]

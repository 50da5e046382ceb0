"""Labellers and their bearer tokens.

A token reads `"<id>.<secret>"`: the id finds the row, and the sha256 of the whole token is
compared with the stored one in constant time. Only the hash is stored; the token is shown once.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections.abc import Collection

from sqlalchemy import Integer, bindparam, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict
from labelqueue.models import LABELLERS, SCRIPTED_TEACHER, Labeller, Query, QueryStatus, Role
from labelqueue.transaction import (
    changed,
    detach,
    get_row,
    reading,
    snapshot,
    transaction,
)


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def check_person_name(name: str) -> None:
    """Conflict for the scripted teacher's name, which no person may take: the worker answers
    for scripted runs as the labeller of that name, whoever holds it (`create_labeller` makes it
    for the worker; an operator's create or rename checks here)."""
    if name == SCRIPTED_TEACHER:
        raise Conflict(f"the name {SCRIPTED_TEACHER!r} is the scripted teacher's (workers answer "
                       "as the labeller of that name); choose another")


def _check_scripted_change(labeller: Labeller, *, active: bool | None, name: str | None) -> None:
    """Conflict for a change that would break the scripted teacher: revoking it leaves scripted
    runs waiting for answers for ever; renaming it, or another to its name, misleads workers."""
    if labeller.name != SCRIPTED_TEACHER:
        if name is not None:
            check_person_name(name)
        return
    if active is False:
        raise Conflict(f"labeller {labeller.id} is the scripted teacher: revoked, runs it "
                       "teaches would wait for answers for ever; stop or switch those runs")
    if name is not None and name != SCRIPTED_TEACHER:
        raise Conflict(f"labeller {labeller.id} is the scripted teacher, found by workers by "
                       f"its name {SCRIPTED_TEACHER!r}: it cannot be renamed")


def create_labeller(
    session: Session, *, name: str, role: Role | str = Role.LABELLER
) -> tuple[Labeller, str]:
    """A new labeller and its bearer token; Conflict if the name is taken."""
    with transaction(session):
        labeller = Labeller(name=name, role=Role(role), token_hash="")
        session.add(labeller)
        try:
            session.flush()
        except IntegrityError as error:
            raise Conflict(f"a labeller named {name!r} already exists") from error
        token = f"{labeller.id}.{secrets.token_urlsafe(32)}"
        labeller.token_hash = hash_token(token)
        detach(session, labeller)
    return labeller, token


_BY_ID = select(*LABELLERS.c).where(LABELLERS.c.id == bindparam("labeller", type_=Integer()))


def authenticate(session: Session, *, token: str) -> Labeller | None:
    """The active labeller whose token this is, or None. Reads in a read-only transaction."""
    labeller_id, dot, _secret = token.partition(".")
    if not dot or not labeller_id.isdigit() or len(labeller_id) > 18:
        return None
    with reading(session):  # a Core statement on the session's connection: no ORM to load
        row = session.connection().execute(_BY_ID, {"labeller": int(labeller_id)}).first()
    if row is None or not row.active:
        return None
    if not hmac.compare_digest(row.token_hash, hash_token(token)):
        return None
    return snapshot(Labeller, row._mapping)


def set_labeller_active(session: Session, *, labeller_id: int, active: bool) -> Labeller:
    """Revoke (or restore) a labeller's access; its labels stay on record."""
    return update_labeller(session, labeller_id=labeller_id, active=active)


def _release_leases(session: Session, *, labeller_id: int) -> None:
    changed(
        session,
        update(Query)
        .where(Query.lease_holder == labeller_id, Query.status == QueryStatus.LEASED)
        .values(
            status=QueryStatus.PENDING, lease_holder=None, lease_expires_at=None, leased_at=None
        ),
    )


def update_labeller(
    session: Session,
    *,
    labeller_id: int,
    active: bool | None = None,
    role: Role | str | None = None,
    name: str | None = None,
) -> Labeller:
    """Change what is given (None keeps it); NotFound, or Conflict if the name is taken, is
    the scripted teacher's, or the change would revoke or rename the scripted teacher.

    Deactivating revokes at once: leasing and answering read `active` in their own transaction,
    and the labeller's leases are released for others. Its labels stay on record.
    """
    with transaction(session):
        labeller = get_row(session, Labeller, labeller_id)
        _check_scripted_change(labeller, active=active, name=name)
        if active is not None:
            labeller.active = active
            if not active:  # others may take its queries at once
                _release_leases(session, labeller_id=labeller_id)
        if role is not None:
            labeller.role = Role(role)
        if name is not None:
            labeller.name = name
        try:
            session.flush()
        except IntegrityError as error:
            raise Conflict(f"a labeller named {name!r} already exists") from error
        detach(session, labeller)
    return labeller


def rotate_token(session: Session, *, labeller_id: int) -> tuple[Labeller, str]:
    """A new bearer token for the labeller; the old one stops working. NotFound if none;
    Conflict for the scripted teacher, whose answers no person may give."""
    with transaction(session):
        labeller = get_row(session, Labeller, labeller_id)
        if labeller.name == SCRIPTED_TEACHER:
            raise Conflict(f"labeller {labeller_id} is the scripted teacher: no person answers "
                           "as it, so it takes no token")
        token = f"{labeller.id}.{secrets.token_urlsafe(32)}"
        labeller.token_hash = hash_token(token)
        detach(session, labeller)
    return labeller, token


def find_labeller(session: Session, *, name: str) -> Labeller | None:
    """The labeller named `name`, or None."""
    with reading(session):
        labeller = session.scalars(
            select(Labeller)
            .where(Labeller.name == name)
            .execution_options(populate_existing=True)
        ).one_or_none()
        if labeller is not None:
            detach(session, labeller)
    return labeller


def labeller_names(session: Session, *, ids: Collection[int]) -> dict[int, str]:
    """The names of the labellers with these ids, by id (an unknown id is left out)."""
    with reading(session):
        rows = session.execute(
            select(Labeller.id, Labeller.name).where(Labeller.id.in_(list(ids)))
        ).all()
    return {labeller_id: name for labeller_id, name in rows}

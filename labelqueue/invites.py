"""Invite links: an operator makes one (for one run or all, with an expiry and at most so many
uses); whoever opens it joins as a new labeller, without a token from the operator.

Joining is one transaction: a conditional UPDATE takes one use of a live invite (not revoked,
not expired, not used up), then the labeller and its token are made. Two people opening the
last use at once: one joins, the other is told the link is used up. An invite may carry a target
number of answers and a completion code, shown to its labellers once they reach the target
(for paid studies).
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Literal

from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict, NotFound, QueueError
from labelqueue.labellers import hash_token
from labelqueue.models import Invite, Invitee, Label, Labeller, LabelSource, Role, Run, utcnow
from labelqueue.transaction import changed, detach, get_row, transaction

PARTICIPANT = re.compile(r"[A-Za-z0-9_.@+-]{1,64}")
"""what a `participant` may be: a crowdsourcing platform's worker id, or a plain name"""
CODE_BYTES = 18
"""random bytes in an invite's code (24 URL-safe characters)"""


class InviteClosed(QueueError):
    """The invite link no longer admits anyone: revoked, expired or used up (`reason`)."""

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason


InviteState = Literal["open", "revoked", "expired", "used_up"]


def invite_state(invite: Invite, now: datetime | None = None) -> InviteState:
    """"open", or why it no longer admits anyone: "revoked", "expired" or "used_up"."""
    now = now or utcnow()
    if invite.revoked_at is not None:
        return "revoked"
    if invite.expires_at <= now:
        return "expired"
    if invite.max_uses is not None and invite.uses >= invite.max_uses:
        return "used_up"
    return "open"


CLOSED_TEXT = {
    "revoked": "This invite link has been withdrawn by the study's organisers.",
    "expired": "This invite link has expired.",
    "used_up": "This invite link has been used as many times as it allows.",
}


def create_invite(
    session: Session,
    *,
    expires_at: datetime,
    run_id: int | None = None,
    max_uses: int | None = None,
    target_answers: int | None = None,
    completion_code: str | None = None,
    note: str | None = None,
) -> Invite:
    """A new invite with a random code. NotFound for an unknown run; ValueError for an expiry
    in the past, a limit below 1, or a completion code without a target answer count. With a
    target and no code, a random code is made."""
    if expires_at <= utcnow():
        raise ValueError("expires_at is in the past: an invite must expire in the future")
    for name, value in (("max_uses", max_uses), ("target_answers", target_answers)):
        if value is not None and value < 1:
            raise ValueError(f"{name} must be at least 1 (or left out), got {value}")
    if completion_code is not None and target_answers is None:
        raise ValueError("completion_code needs target_answers: the number of answers after "
                         "which it is shown")
    if target_answers is not None and completion_code is None:
        completion_code = secrets.token_hex(4).upper()
    with transaction(session):
        if run_id is not None:
            get_row(session, Run, run_id)
        invite = Invite(
            code=secrets.token_urlsafe(CODE_BYTES), run_id=run_id, note=note,
            expires_at=expires_at, max_uses=max_uses, uses=0, target_answers=target_answers,
            completion_code=completion_code,
        )
        session.add(invite)
        detach(session, invite)
    return invite


def list_invites(session: Session) -> list[Invite]:
    with transaction(session):
        return list(session.scalars(select(Invite).order_by(Invite.id)))


def read_invite(session: Session, *, code: str) -> Invite | None:
    """The invite with this code, or None."""
    with transaction(session):
        invite = session.scalars(
            select(Invite).where(Invite.code == code).execution_options(populate_existing=True)
        ).one_or_none()
        if invite is not None:
            detach(session, invite)
    return invite


def revoke_invite(session: Session, *, invite_id: int) -> Invite:
    """Stop the invite admitting anyone (again: no change). Labellers who joined by it keep
    their access (revoke them one by one). NotFound for an unknown invite."""
    with transaction(session):
        invite = get_row(session, Invite, invite_id)
        if invite.revoked_at is None:
            invite.revoked_at = utcnow()
        detach(session, invite)
    return invite


@dataclass(frozen=True)
class Joined:
    """A labeller made by an invite, with its bearer token (shown this once)."""

    labeller: Labeller
    token: str
    invite: Invite


def join_invite(session: Session, *, code: str, participant: str | None = None) -> Joined:
    """A new labeller, named after `participant` (else "guest-<hex>"; "-2", "-3", ... when the
    name is taken). NotFound for an unknown code; InviteClosed when the invite is revoked,
    expired or used up; ValueError for a `participant` that is not 1-64 of A-Z a-z 0-9 _ . @ + -.
    """
    if participant is not None and not PARTICIPANT.fullmatch(participant):
        raise ValueError("participant must be 1 to 64 letters, digits or _ . @ + - "
                         f"(got {participant[:80]!r})")
    now = utcnow()
    with transaction(session):
        took = changed(
            session,
            update(Invite)
            .where(
                Invite.code == code,
                Invite.revoked_at.is_(None),
                Invite.expires_at > now,
                or_(Invite.max_uses.is_(None), Invite.uses < Invite.max_uses),
            )
            .values(uses=Invite.uses + 1),
        )
        invite = session.scalars(
            select(Invite).where(Invite.code == code).execution_options(populate_existing=True)
        ).one_or_none()
        if invite is None:
            raise NotFound("no such invite link: check that it was copied whole")
        if not took:
            state = invite_state(invite, now)
            reason = "used_up" if state == "open" else state  # the last use went meanwhile
            raise InviteClosed(CLOSED_TEXT[reason], reason)
        name = _free_name(session, participant or f"guest-{secrets.token_hex(3)}")
        labeller = Labeller(name=name, role=Role.LABELLER, token_hash="")
        session.add(labeller)
        try:
            session.flush()
        except IntegrityError as error:  # another join took the name meanwhile (PostgreSQL)
            raise Conflict(f"the labeller name {name!r} was just taken; open the link again") \
                from error
        token = f"{labeller.id}.{secrets.token_urlsafe(32)}"
        labeller.token_hash = hash_token(token)
        session.add(Invitee(labeller_id=labeller.id, invite_id=invite.id,
                            participant=participant, joined_at=now))
        detach(session, labeller, invite)
    return Joined(labeller=labeller, token=token, invite=invite)


def _free_name(session: Session, base: str) -> str:
    taken = set(session.scalars(
        select(Labeller.name).where(or_(Labeller.name == base, Labeller.name.like(f"{base}-%")))
    ))
    if base not in taken:
        return base
    return next(f"{base}-{n}" for n in range(2, len(taken) + 3) if f"{base}-{n}" not in taken)


@dataclass(frozen=True)
class Progress:
    """A labeller's answers so far, against its invite's target (if any)."""

    labels: int
    target_answers: int | None
    completion_code: str | None
    """shown only once `labels` reaches the target"""
    run_id: int | None
    """the run its invite was for; none: all runs, or no invite"""


def labeller_progress(session: Session, *, labeller_id: int) -> Progress:
    """How far the labeller is: its answers given by hand (skips included, answers taken back
    not), and, for one who joined by an invite with a target, the completion code once the
    target is reached."""
    with transaction(session):
        labels = session.scalar(
            select(func.count(Label.id)).where(
                Label.labeller_id == labeller_id, Label.source == LabelSource.HUMAN,
                Label.withdrawn_at.is_(None),
            )
        ) or 0
        invite = session.scalars(
            select(Invite).join(Invitee, Invitee.invite_id == Invite.id)
            .where(Invitee.labeller_id == labeller_id)
        ).one_or_none()
    if invite is None:
        return Progress(labels, None, None, None)
    reached = invite.target_answers is not None and labels >= invite.target_answers
    return Progress(labels, invite.target_answers, invite.completion_code if reached else None,
                    invite.run_id)

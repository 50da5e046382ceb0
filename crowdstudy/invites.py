"""Invite links: an operator makes one (for one run or all, with an expiry and at most so many
uses); whoever opens it joins as a new labeller, without a token from the operator.

Joining is one transaction: a conditional UPDATE takes one use of a live invite (not revoked,
not expired, not used up, its runs not over), then the labeller and its token are made. Two
people opening the last use at once: one joins, the other is told the link is used up.

An invite is a study: its state follows its runs (`closed` once none of them can give pairs
any more: stopped, finished, failed or its budget spent, `live_runs`), it may carry a consent
text (nobody joins without agreeing), a target number of answers, a completion redirect URL
and what a participant paused by check pairs is told. How far each participant is, and their
completion code, are `crowdstudy.completion`'s.

An all-runs invite's entry test is taken on the practice pairs of whichever of its runs has
them (`labelqueue.entry_test`): one is refused while runs are open and none has enough practice
pairs, and one whose runs lose them later is said to lack them (`entry_test_missing`), to its
operator and to each participant who waits on the test with nothing to label.
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass
from datetime import datetime
from typing import Literal
from urllib.parse import urlsplit

from sqlalchemy import ColumnElement, exists, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.entry_test import EntryPassInvalid, check_entry_pass
from labelqueue.errors import Conflict, Invalid, NotFound, QueueError, Revoked
from labelqueue.labellers import hash_token
from labelqueue.models import (
    RUNS,
    Invite,
    Invitee,
    Labeller,
    Role,
    Run,
    RunStatus,
    TeacherKind,
    utcnow,
)
from labelqueue.practice import practice_pairs
from labelqueue.run_config import FEEDBACK, run_feedback
from labelqueue.runs import budget_spent
from labelqueue.transaction import changed, detach, get_row, reading, transaction
from runvocab.text import filled

PARTICIPANT = re.compile(r"[A-Za-z0-9_.@+-]{1,64}")
"""what a `participant` may be: a crowdsourcing platform's worker id, or a plain name"""
CODE_BYTES = 18
"""random bytes in an invite's code (24 URL-safe characters)"""
CODE = re.compile(r"[A-Za-z0-9_-]{1,64}")
"""what an invite's code can be: anything else (a NUL character, say) is no invite's, and is
not looked up"""
RUN_OPEN = (RunStatus.QUEUED, RunStatus.RUNNING, RunStatus.PAUSED)
"""a run in one of these may still give pairs to label, while its budget pays for one more
query; stopping, stopped, finished and failed runs never will (a requeued run opens its
invites again). An all-runs invite closes once every run taught by people is over."""
REDIRECT_MAX = 2000


class InviteClosed(QueueError):
    """The invite link no longer admits anyone: revoked, expired, used up or its runs are over
    (`reason`)."""

    def __init__(self, message: str, reason: str):
        super().__init__(message)
        self.reason = reason


InviteState = Literal["open", "revoked", "expired", "used_up", "closed"]


def invite_state(invite: Invite, now: datetime | None = None,
                 runs_open: bool = True) -> InviteState:
    """"open", or why it no longer admits anyone: "revoked", "expired", "used_up", or "closed"
    when its runs are over (`runs_open`, from `invite_runs_open`)."""
    now = now or utcnow()
    if invite.revoked_at is not None:
        return "revoked"
    if invite.expires_at <= now:
        return "expired"
    if invite.max_uses is not None and invite.uses >= invite.max_uses:
        return "used_up"
    if not runs_open:
        return "closed"
    return "open"


CLOSED_TEXT = {
    "revoked": "This invite link has been withdrawn by the study's organisers.",
    "expired": "This invite link has expired.",
    "used_up": "This invite link has been used as many times as it allows.",
    "closed": "This study has ended: its training run is over, so there are no more clips to "
              "label.",
}


def live_runs(session: Session, run_id: int | None) -> list[int]:
    """The ids of the runs that may still give an invite's participants pairs: its run (`run_id`;
    None: every run taught by people) if it is queued, running or paused and its budget pays for
    one more query (`labelqueue.runs.budget_spent`). Call it inside a transaction."""
    which = Run.id == run_id if run_id is not None else Run.teacher == TeacherKind.HUMAN
    return _live(session, which)


def _live(session: Session, which: ColumnElement[bool]) -> list[int]:
    # The budget's test needs the run's config (labels per query), so it is made here, not in SQL.
    runs = session.scalars(select(Run).where(which, Run.status.in_(RUN_OPEN))
                           .execution_options(populate_existing=True)).all()
    return [run.id for run in runs if not budget_spent(run)]


def runs_open(session: Session, run_id: int | None) -> bool:
    """Whether an invite's runs may still give pairs (`live_runs`); an all-runs invite is open
    too while no run taught by people was ever made (an operator may make the link before the
    runs). Call it inside a transaction."""
    if live_runs(session, run_id):
        return True
    return run_id is None and not session.scalar(
        select(exists().where(Run.teacher == TeacherKind.HUMAN)))


ENTRY_TEST_WAIT = (
    "This study starts with an entry test on practice pairs, and none of its runs has practice "
    "pairs to give you now, so there is nothing for you to label yet. The study's organisers "
    "can see this on their side. Keep this page open: the practice pairs appear here by "
    "themselves once a run has them, and if none comes within the study's wait, you finish "
    "with your completion code.")
"""what a participant waiting on an entry test that no open run can give is told"""


def _short_of_practice(session: Session, run_id: int | None, entry_pass: int) -> list[int]:
    """The invite's open runs (`live_runs`) when none of them has `entry_pass` practice pairs
    (`feedback.practice_pairs`), so none can give its entry test; [] when one can, or when none
    is open. Call it inside a transaction."""
    live = live_runs(session, run_id)
    if not live:
        return []
    rows = session.execute(select(RUNS.c.config, FEEDBACK).where(RUNS.c.id.in_(live))).all()
    return [] if any(practice_pairs(run_feedback(row)) >= entry_pass for row in rows) else live


def entry_test_missing(session: Session, invite: Invite) -> str | None:
    """For the invite's operator: why its participants cannot take its entry test now (open
    runs, none with enough practice pairs: they are served nothing, and on a run with fewer
    they would fail it); None when nothing is missing, or the invite has no entry test."""
    if invite.entry_pass is None:
        return None
    with reading(session):
        short = _short_of_practice(session, invite.run_id, invite.entry_pass)
    if not short:
        return None
    return (f"none of its open runs ({', '.join(map(str, short))}) has at least "
            f"{invite.entry_pass} practice pairs (feedback.practice_pairs) for its entry test: "
            "its participants are served nothing to label until one has, and would fail the "
            "test on a run with fewer")


def waits_on_entry_test(session: Session, *, labeller_id: int) -> bool:
    """Whether the labeller's entry test is undecided and no open run of their invite can give
    it (`entry_test_missing`): what they wait on is that, not the runs."""
    with reading(session):
        invite = session.scalar(select(Invite).join(Invitee, Invitee.invite_id == Invite.id)
                                .where(Invitee.labeller_id == labeller_id,
                                       Invitee.entry_passed.is_(None)))
        if invite is None or invite.entry_pass is None:
            return False
        return bool(_short_of_practice(session, invite.run_id, invite.entry_pass))


def invite_runs_open(session: Session, invites: list[Invite]) -> dict[int, bool]:
    """Whether each invite's runs may still give pairs (`runs_open`), by invite id."""
    with reading(session):
        run_ids = {invite.run_id for invite in invites if invite.run_id is not None}
        live = set(_live(session, Run.id.in_(run_ids))) if run_ids else set()
        any_open = (any(invite.run_id is None for invite in invites)
                    and runs_open(session, None))
    return {invite.id: (any_open if invite.run_id is None else invite.run_id in live)
            for invite in invites}


def check_redirect_url(url: str | None) -> str | None:
    """The URL as stored; Invalid unless it is an absolute http(s) URL of at most 2000
    characters."""
    if url is None:
        return None
    url = url.strip()
    try:
        parts = urlsplit(url)
    except ValueError as err:  # an unclosed [ in the host, characters NFKC turns into / or @
        raise Invalid(f"redirect_url cannot be read as a URL: {err} (got {url[:80]!r})") \
            from None
    if parts.scheme not in ("http", "https") or not parts.netloc or len(url) > REDIRECT_MAX:
        raise Invalid("redirect_url must be an absolute http:// or https:// URL of at most "
                         f"{REDIRECT_MAX} characters (got {url[:80]!r})")
    if "{" in parts.netloc or "}" in parts.netloc:
        raise Invalid("redirect_url: {participant} and {code} may be filled in the path or "
                         f"the query, never the host (got {parts.netloc[:80]!r})")
    return url


def create_invite(
    session: Session,
    *,
    expires_at: datetime,
    run_id: int | None = None,
    max_uses: int | None = None,
    target_answers: int | None = None,
    completion_code: str | None = None,
    note: str | None = None,
    redirect_url: str | None = None,
    consent_text: str | None = None,
    pause_message: str | None = None,
    wait_limit_s: int | None = None,
    entry_pass: int | None = None,
) -> Invite:
    """A new invite with a random code. NotFound for an unknown run; Invalid for an expiry
    in the past, a limit below 1 or a redirect URL that is not http(s). `completion_code`: the
    study's code, the prefix of each participant's own (`participant_code`). `wait_limit_s`:
    a participant who asked this long with nothing to label finishes with their code
    (`labelqueue.waiting`; None: `WAIT_LIMIT_S`). `entry_pass`: an entry test, the practice
    answers of the run's `feedback.practice_pairs` a participant must get right to go on
    (`labelqueue.entry_test`; Invalid unless from 1 to the run's practice pairs). `note`,
    `consent_text` and `pause_message` are stored without their outer white space; Invalid
    for one that is nothing else (a consent text of spaces would ask no consent)."""
    if expires_at <= utcnow():
        raise Invalid("expires_at is in the past: an invite must expire in the future")
    for name, value in (("max_uses", max_uses), ("target_answers", target_answers),
                        ("wait_limit_s", wait_limit_s)):
        if value is not None and value < 1:
            raise Invalid(f"{name} must be at least 1 (or left out), got {value}")
    redirect_url = check_redirect_url(redirect_url)
    note, consent_text, pause_message = (_filled(name, text) for name, text in (
        ("note", note), ("consent_text", consent_text), ("pause_message", pause_message)))
    with transaction(session):
        if run_id is not None:
            get_row(session, Run, run_id)
        check_entry_pass(session, run_id=run_id, entry_pass=entry_pass)
        short = (_short_of_practice(session, None, entry_pass)
                 if run_id is None and entry_pass is not None else [])
        if short:
            raise EntryPassInvalid(
                f"entry_pass needs a run with at least {entry_pass} practice pairs "
                f"(feedback.practice_pairs), and none of the open runs taught by people "
                f"({', '.join(map(str, short))}) has that many: make one first, or leave "
                "entry_pass out")
        invite = Invite(
            code=secrets.token_urlsafe(CODE_BYTES), run_id=run_id, note=note,
            expires_at=expires_at, max_uses=max_uses, uses=0, target_answers=target_answers,
            completion_code=completion_code, redirect_url=redirect_url,
            consent_text=consent_text, pause_message=pause_message, wait_limit_s=wait_limit_s,
            entry_pass=entry_pass,
        )
        session.add(invite)
        detach(session, invite)
    return invite


def _filled(name: str, text: str | None) -> str | None:
    """`text` without its outer white space; Invalid when that is all it holds."""
    if text is None:
        return None
    try:
        return filled(text, name)
    except ValueError as err:
        raise Invalid(f"{err}, or leave it out") from None


def list_invites(session: Session) -> list[Invite]:
    """Every invite, oldest first (a read: on SQLite it takes no write lock)."""
    with reading(session):
        return list(session.scalars(select(Invite).order_by(Invite.id)
                                    .execution_options(populate_existing=True)))


def read_invite(session: Session, *, code: str) -> Invite | None:
    """The invite with this code, or None (a read: on SQLite it takes no write lock, so
    anyone opening a link, unauthenticated, never waits for a writer nor makes one wait)."""
    if not CODE.fullmatch(code):
        return None
    with reading(session):
        invite = session.scalars(
            select(Invite).where(Invite.code == code).execution_options(populate_existing=True)
        ).one_or_none()
        if invite is not None:
            session.expunge(invite)
    return invite


def invite_run(session: Session, *, labeller_id: int) -> int | None:
    """The one run the labeller's invite is for; None for an all-runs invite, or a labeller
    who joined by none."""
    with reading(session):
        return session.scalar(select(Invite.run_id).join(Invitee, Invitee.invite_id == Invite.id)
                              .where(Invitee.labeller_id == labeller_id))


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
    rejoined: bool = False
    """the participant had joined before: their labeller, with a new token"""


def join_invite(session: Session, *, code: str, participant: str | None = None,
                consent: bool = False) -> Joined:
    """A new labeller, named after `participant` (else "guest-<hex>"; "-2", "-3", ... when the
    name is taken). NotFound for an unknown code; InviteClosed when the invite is revoked,
    expired, used up or its runs are over; Invalid for a `participant` that is not 1-64 of
    A-Z a-z 0-9 _ . @ + -, or without `consent` to an invite that has a consent text.

    One person, one labeller: a `participant` who joined the invite before (from another
    browser, or again) gets the same labeller back, with a new token (the old one stops), and
    takes no use of the link, even a used-up one; their answers, count and code are theirs
    still. Revoked for a participant whose labeller was deactivated.
    """
    if participant is not None and not PARTICIPANT.fullmatch(participant):
        raise Invalid("participant must be 1 to 64 letters, digits or _ . @ + - "
                         f"(got {participant[:80]!r})")
    if not CODE.fullmatch(code):
        raise NotFound("no such invite link: check that it was copied whole")
    now = utcnow()
    with transaction(session):
        # Joins by one link take turns (a row lock on PostgreSQL; SQLite's writes do anyway),
        # so one participant's two joins at once make one labeller.
        invite = session.scalars(
            select(Invite).where(Invite.code == code).with_for_update()
            .execution_options(populate_existing=True)
        ).one_or_none()
        if invite is None:
            raise NotFound("no such invite link: check that it was copied whole")
        if invite.consent_text and not consent:
            raise Invalid("this study asks for consent first: read its consent text on the "
                             "invite's page and agree to it (consent: true)")
        if participant is not None:
            again = _rejoin(session, invite, participant, now)
            if again is not None:
                return again
        open_now = runs_open(session, invite.run_id)
        took = open_now and changed(
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
        session.refresh(invite)
        if not took:
            state = invite_state(invite, now, open_now)
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


def _rejoin(session: Session, invite: Invite, participant: str, now: datetime) -> Joined | None:
    """The participant's labeller on the invite, with a new token; None when they never joined.
    A link revoked, expired or whose runs are over admits nobody, not even again."""
    labeller = session.scalars(
        select(Labeller).join(Invitee, Invitee.labeller_id == Labeller.id)
        .where(Invitee.invite_id == invite.id, Invitee.participant == participant)
        .order_by(Labeller.id).limit(1)
    ).one_or_none()
    if labeller is None:
        return None
    state = invite_state(invite, now, runs_open(session, invite.run_id))
    if state not in ("open", "used_up"):
        raise InviteClosed(CLOSED_TEXT[state], state)
    if not labeller.active:
        raise Revoked(f"participant {participant}'s labeller is deactivated on this study")
    token = f"{labeller.id}.{secrets.token_urlsafe(32)}"
    labeller.token_hash = hash_token(token)
    detach(session, labeller, invite)
    return Joined(labeller=labeller, token=token, invite=invite, rejoined=True)


def _free_name(session: Session, base: str) -> str:
    taken = set(session.scalars(
        select(Labeller.name).where(or_(Labeller.name == base, Labeller.name.like(f"{base}-%")))
    ))
    if base not in taken:
        return base
    return next(f"{base}-{n}" for n in range(2, len(taken) + 3) if f"{base}-{n}" not in taken)

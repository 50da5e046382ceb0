"""Invite links: an operator makes one (for one run or all, with an expiry and at most so many
uses); whoever opens it joins as a new labeller, without a token from the operator.

Joining is one transaction: a conditional UPDATE takes one use of a live invite (not revoked,
not expired, not used up, its runs not over), then the labeller and its token are made. Two
people opening the last use at once: one joins, the other is told the link is used up.

An invite is a study: its state follows its runs (`closed` once none of them can give pairs
any more), it may carry a consent text (nobody joins without agreeing), a target number of
answers, a completion redirect URL and what a participant paused by check pairs is told. Each
participant's study ends with their own completion code (`participant_code`: derived from the
invite and the labeller with a key the server keeps, so it cannot be guessed or shared), shown
once the target is reached, once the invite's runs are over, or on a pause; an operator checks
a code with `verify_code`. Only decisive answers (`runvocab.answers.DECISIVE`) on the invite's
own runs count towards the target: skips, can't-tells and answers on other runs do not.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass, replace
from datetime import datetime
from typing import Literal
from urllib.parse import parse_qsl, quote, urlencode, urlsplit, urlunsplit

from sqlalchemy import ColumnElement, exists, func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.entry_test import check_entry_pass
from labelqueue.errors import Conflict, Invalid, NotFound, QueueError, Revoked
from labelqueue.keys import server_key
from labelqueue.labellers import hash_token
from labelqueue.models import (
    Invite,
    Invitee,
    Label,
    Labeller,
    LabellerPause,
    LabelSource,
    Role,
    Run,
    RunStatus,
    TeacherKind,
    utcnow,
)
from labelqueue.runs import budget_spent
from labelqueue.transaction import changed, detach, get_row, reading, transaction
from runvocab.answers import DECISIVE

PARTICIPANT = re.compile(r"[A-Za-z0-9_.@+-]{1,64}")
"""what a `participant` may be: a crowdsourcing platform's worker id, or a plain name"""
CODE_BYTES = 18
"""random bytes in an invite's code (24 URL-safe characters)"""
RUN_OPEN = (RunStatus.QUEUED, RunStatus.RUNNING, RunStatus.PAUSED)
"""a run in one of these may still give pairs to label; stopping, stopped, finished and failed
runs never will (a requeued run opens its invites again). An all-runs invite closes once every
run taught by people is over."""
REDIRECT_MAX = 2000
CODE_ALPHABET = "0123456789ABCDEFGHJKMNPQRSTVWXYZ"
"""Crockford's base 32: no I, L, O or U, so a code read aloud or retyped survives"""
CODE_GROUPS = 3
"""a participant's own part: three groups of four characters (60 bits of an HMAC)"""


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


def _open_runs_of(run_id: int | None) -> ColumnElement[bool]:
    """A condition: the run `run_id` is open; for an all-runs invite, some run taught by people
    is, or none was ever made (an operator may make the link before the runs)."""
    if run_id is not None:
        return exists().where(Run.id == run_id, Run.status.in_(RUN_OPEN))
    return or_(exists().where(Run.teacher == TeacherKind.HUMAN, Run.status.in_(RUN_OPEN)),
               ~exists().where(Run.teacher == TeacherKind.HUMAN))


def invite_runs_open(session: Session, invites: list[Invite]) -> dict[int, bool]:
    """Whether each invite's runs may still give pairs: its run is queued, running or paused
    (for an all-runs invite: some run taught by people is), by invite id."""
    with reading(session):
        run_ids = {invite.run_id for invite in invites if invite.run_id is not None}
        open_ids = set(session.scalars(
            select(Run.id).where(Run.id.in_(run_ids), Run.status.in_(RUN_OPEN))
        )) if run_ids else set()
        any_open = (any(invite.run_id is None for invite in invites)
                    and bool(session.scalar(select(_open_runs_of(None)))))
    return {invite.id: (any_open if invite.run_id is None else invite.run_id in open_ids)
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
    (`labelqueue.entry_test`; Invalid unless from 1 to the run's practice pairs)."""
    if expires_at <= utcnow():
        raise Invalid("expires_at is in the past: an invite must expire in the future")
    for name, value in (("max_uses", max_uses), ("target_answers", target_answers),
                        ("wait_limit_s", wait_limit_s)):
        if value is not None and value < 1:
            raise Invalid(f"{name} must be at least 1 (or left out), got {value}")
    redirect_url = check_redirect_url(redirect_url)
    with transaction(session):
        if run_id is not None:
            get_row(session, Run, run_id)
        check_entry_pass(session, run_id=run_id, entry_pass=entry_pass)
        invite = Invite(
            code=secrets.token_urlsafe(CODE_BYTES), run_id=run_id, note=note,
            expires_at=expires_at, max_uses=max_uses, uses=0, target_answers=target_answers,
            completion_code=completion_code, redirect_url=redirect_url,
            consent_text=(consent_text or "").strip() or None,
            pause_message=(pause_message or "").strip() or None, wait_limit_s=wait_limit_s,
            entry_pass=entry_pass,
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
        took = changed(
            session,
            update(Invite)
            .where(
                Invite.code == code,
                Invite.revoked_at.is_(None),
                Invite.expires_at > now,
                or_(Invite.max_uses.is_(None), Invite.uses < Invite.max_uses),
                _open_runs_of(invite.run_id),
            )
            .values(uses=Invite.uses + 1),
        )
        session.refresh(invite)
        if not took:
            runs_open = bool(session.scalar(select(_open_runs_of(invite.run_id))))
            state = invite_state(invite, now, runs_open)
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
    runs_open = bool(session.scalar(select(_open_runs_of(invite.run_id))))
    state = invite_state(invite, now, runs_open)
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


# ---- completion codes ------------------------------------------------------------------------

def _own_part(key: bytes, invite_id: int, labeller_id: int) -> str:
    digest = hmac.new(key, f"completion:{invite_id}:{labeller_id}".encode(),
                      hashlib.sha256).digest()
    bits = int.from_bytes(digest[:8], "big") >> 4  # 60 bits
    chars = "".join(CODE_ALPHABET[(bits >> (5 * i)) & 31] for i in range(4 * CODE_GROUPS))
    return "-".join(chars[i:i + 4] for i in range(0, len(chars), 4))


def participant_code(key: bytes, invite: Invite, labeller_id: int) -> str:
    """The participant's own completion code: the invite's study code (if it has one), then
    twelve characters of an HMAC of the invite and the labeller under the server's key
    (`labelqueue.keys`). Nobody without the key can make another participant's code, and two
    participants never share one."""
    own = _own_part(key, invite.id, labeller_id)
    return f"{invite.completion_code}-{own}" if invite.completion_code else own


def _normalised(code: str) -> str:
    code = re.sub(r"\s+", "", code).upper()
    return code.translate(str.maketrans("OIL", "011"))


@dataclass(frozen=True)
class Verified:
    """A completion code an operator checked: whose it is and how far they got."""

    invite_id: int
    labeller_id: int
    labeller: str
    participant: str | None
    run_id: int | None
    counted: int
    """decisive answers on the invite's runs (what the target counts)"""
    target_answers: int | None
    complete: bool
    why: str | None
    """"target", "runs_over", "paused", "nothing_left" or "entry_failed" (see `Progress.why`)"""

    @property
    def earned(self) -> bool:
        """the code is earned: the study is complete, and not by failing the entry test"""
        return self.complete and self.why != "entry_failed"


def verify_code(session: Session, code: str) -> Verified | None:
    """Whose completion code this is, or None when it is no participant's. The study-code prefix
    may be left out; case, spaces, and O/0, I/L/1 confusions do not matter."""
    given = _normalised(code)
    groups = given.split("-")
    if len(groups) < CODE_GROUPS:
        return None
    own = "-".join(groups[-CODE_GROUPS:])
    prefix = "-".join(groups[:-CODE_GROUPS])
    key = server_key(session)
    with reading(session):
        rows = session.execute(
            select(Invitee.labeller_id, Invite)
            .join(Invite, Invite.id == Invitee.invite_id)
            .order_by(Invitee.labeller_id)
        ).all()
        session.expunge_all()
    for labeller_id, invite in rows:
        if not hmac.compare_digest(_own_part(key, invite.id, labeller_id), own):
            continue
        if prefix and _normalised(invite.completion_code or "") != prefix:
            return None
        progress = labeller_progress(session, labeller_id=labeller_id)
        with reading(session):
            name = session.scalar(select(Labeller.name).where(Labeller.id == labeller_id))
        return Verified(invite.id, labeller_id, name or "", progress.participant, invite.run_id,
                        progress.counted, invite.target_answers, progress.complete, progress.why)
    return None


def completion_redirect(url: str, *, code: str, participant: str | None) -> str:
    """The invite's redirect URL for one participant: `{code}` and `{participant}` in it filled
    in (URL-encoded); a URL without either gets `participant` (when known) added to its query,
    so a platform learns whose session ended."""
    if "{code}" in url or "{participant}" in url:
        return url.replace("{code}", quote(code, safe="")).replace(
            "{participant}", quote(participant or "", safe=""))
    if participant is None:
        return url
    parts = urlsplit(url)
    query = parse_qsl(parts.query, keep_blank_values=True) + [("participant", participant)]
    return urlunsplit(parts._replace(query=urlencode(query)))


# ---- a participant's progress ------------------------------------------------------------------

@dataclass(frozen=True)
class Progress:
    """A labeller's answers so far and, for one who joined by an invite, where their study
    stands."""

    labels: int
    """answers given by hand on any run (skips included, answers taken back not)"""
    target_answers: int | None
    completion_code: str | None
    """the participant's own code, once their study is complete (none before, and none for a
    paused participant whose invite has a `pause_message`)"""
    run_id: int | None
    """the run its invite was for; none: all runs, or no invite"""
    counted: int = 0
    """what the target counts: decisive answers on the invite's runs (`labels` without one)"""
    invited: bool = False
    complete: bool = False
    why: str | None = None
    """why the study is complete: "target" (reached), "runs_over" (its runs ended, or the run's
    budget is spent), "paused" (check pairs paused the participant) or "nothing_left" (they
    asked for pairs and got none for the invite's `wait_limit_s`: `labelqueue.waiting`) or
    "entry_failed" (they answered every practice pair with fewer right than the invite's
    `entry_pass`: `labelqueue.entry_test`; let go without a code)"""
    participant: str | None = None
    redirect_url: str | None = None
    """where to send the participant now, filled in for them; none until complete"""
    pause_message: str | None = None
    """the operator's words for a paused participant, or one who failed the entry test (given
    instead of the code)"""
    entry_correct: int | None = None
    """practice answers they got right, once the invite's entry test is decided"""
    entry_pass: int | None = None
    """the invite's entry test: practice answers to get right; none: no test"""

    @property
    def earned(self) -> bool:
        """the code is earned: the study is complete, and not by failing the entry test"""
        return self.complete and self.why != "entry_failed"


def labeller_progress(session: Session, *, labeller_id: int) -> Progress:
    """How far the labeller is. For one who joined by an invite: decisive answers on the
    invite's runs against its target (practice answers never count), and whether the study is
    complete for them (target reached, runs over or budget spent, paused by check pairs, or
    nothing left to label after waiting), with their own code; or let go without one, having
    failed the invite's entry test (which comes before every other end)."""
    with reading(session):
        standing = (Label.labeller_id == labeller_id, Label.source == LabelSource.HUMAN,
                    Label.withdrawn_at.is_(None))
        labels = session.scalar(select(func.count(Label.id)).where(*standing)) or 0
        row = session.execute(
            select(Invite, Invitee.participant, Invitee.nothing_left_at, Invitee.entry_passed,
                   Invitee.entry_correct)
            .join(Invitee, Invitee.invite_id == Invite.id)
            .where(Invitee.labeller_id == labeller_id)
        ).one_or_none()
        if row is None:
            return Progress(labels, None, None, None, counted=labels)
        invite, participant, nothing_left, entry_passed, entry_correct = row
        on_runs = [Label.run_id == invite.run_id] if invite.run_id is not None else []
        # Practice answers never count toward a target (labelqueue.practice).
        counted = session.scalar(select(func.count(Label.id)).where(
            *standing, Label.answer.in_(DECISIVE), Label.practice.is_(False), *on_runs)) or 0
        if invite.run_id is not None:
            run = session.get(Run, invite.run_id)
            assert run is not None
            over = run.status not in RUN_OPEN or budget_spent(run)
            paused = session.scalar(select(exists().where(
                LabellerPause.run_id == run.id, LabellerPause.labeller_id == labeller_id)))
        else:
            over = not session.scalar(select(_open_runs_of(None)))
            # Paused on every open run: nothing more for them anywhere.
            unpaused = exists().where(
                Run.teacher == TeacherKind.HUMAN, Run.status.in_(RUN_OPEN),
                ~exists().where(LabellerPause.run_id == Run.id,
                                LabellerPause.labeller_id == labeller_id))
            paused = not over and not session.scalar(select(unpaused))
        session.expunge_all()
    reached = invite.target_answers is not None and counted >= invite.target_answers
    failed = entry_passed is not None and not entry_passed
    why = ("entry_failed" if failed else "target" if reached else "runs_over" if over
           else "paused" if paused else "nothing_left" if nothing_left is not None else None)
    progress = Progress(labels, invite.target_answers, None, invite.run_id, counted=counted,
                        invited=True, complete=why is not None, why=why,
                        participant=participant, entry_correct=entry_correct,
                        entry_pass=invite.entry_pass)
    if why is None:
        return progress
    if why == "entry_failed":  # let go: no code, no redirect; the study's own words if any
        return replace(progress, pause_message=invite.pause_message)
    if why == "paused" and invite.pause_message:
        return replace(progress, pause_message=invite.pause_message)
    code = participant_code(server_key(session), invite, labeller_id)
    redirect = (completion_redirect(invite.redirect_url, code=code, participant=participant)
                if invite.redirect_url else None)
    return replace(progress, completion_code=code, redirect_url=redirect)

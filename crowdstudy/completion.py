"""Where a participant's study stands, and their completion code.

Each participant's study ends with their own completion code (`participant_code`: derived from
the invite and the labeller with a key the server keeps, so it cannot be guessed or shared),
shown once the target is reached, once the invite's runs are over, or on a pause; an operator
checks a code with `verify_code`. Only decisive answers (`runvocab.answers.DECISIVE`) on the
invite's own runs count towards the target: skips, can't-tells and answers on other runs do
not.

A completion with a code is kept once found (`invitees.completed_at`, `completed_why`): the
participant may have been shown their code, so it stays earned, for the same reason, whatever
their runs do later (a run requeued, a pause lifted) and though they label more.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any
from urllib.parse import parse_qsl, quote, urlencode, urlsplit, urlunsplit

from sqlalchemy import and_, case, func, select, update
from sqlalchemy.orm import Session

from crowdstudy.invites import live_runs, runs_open
from labelqueue.keys import server_key
from labelqueue.models import (
    Invite,
    Invitee,
    Label,
    Labeller,
    LabellerPause,
    LabelSource,
    utcnow,
)
from labelqueue.transaction import changed, reading, transaction
from runvocab.answers import DECISIVE

CODE_ALPHABET = "0123456789ABCDEFGHJKMNPQRSTVWXYZ"
"""Crockford's base 32: no I, L, O or U, so a code read aloud or retyped survives"""
CODE_GROUPS = 3
"""a participant's own part: three groups of four characters (60 bits of an HMAC)"""


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


OWN_CHARS = 4 * CODE_GROUPS
"""characters of a participant's own part, its dashes left out"""


def _normalised(code: str) -> str:
    """The code as compared: without white space or dashes (a code typed in groups, split
    anywhere, is one code), in capitals, with O, I and L read as 0, 1 and 1."""
    code = re.sub(r"[\s-]+", "", code).upper()
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
    earned: bool = False
    """the code is earned (`Progress.earned`): pay them"""


@dataclass(frozen=True)
class Owner:
    """Whose completion code it is: a participant of an invite."""

    labeller_id: int
    labeller: str
    participant: str | None
    invite: Invite


def code_owners(session: Session) -> dict[str, Owner]:
    """Every participant's own part of their code (`OWN_CHARS`, without dashes), with whose it
    is: one HMAC per participant, made once however many codes are then checked."""
    key = server_key(session)
    with reading(session):
        rows = session.execute(
            select(Invitee.labeller_id, Labeller.name, Invitee.participant, Invite)
            .join(Invite, Invite.id == Invitee.invite_id)
            .join(Labeller, Labeller.id == Invitee.labeller_id)
        ).all()
        session.expunge_all()
    return {_own_part(key, invite.id, labeller_id).replace("-", ""):
            Owner(labeller_id, name, participant, invite)
            for labeller_id, name, participant, invite in rows}


def code_owner(owners: dict[str, Owner], code: str) -> Owner | None:
    """Whose completion code this is (`owners`: from `code_owners`), or None when it is no
    participant's. The study-code prefix may be left out (a wrong one makes it nobody's);
    case, spaces, dashes, and O/0, I/L/1 confusions do not matter."""
    given = _normalised(code)
    if len(given) < OWN_CHARS:
        return None
    # The own part is the last twelve characters; the rest is the study code, if given.
    own, prefix = given[-OWN_CHARS:], given[:-OWN_CHARS]
    owner = owners.get(own)
    if owner is None or prefix and _normalised(owner.invite.completion_code or "") != prefix:
        return None
    return owner


def verify_code(session: Session, code: str) -> Verified | None:
    """Whose completion code this is and how far they got, or None when it is no participant's
    (`code_owner`; checking many codes, make `code_owners` once and call `verified`)."""
    owner = code_owner(code_owners(session), code)
    return None if owner is None else verified(session, owner)


def verified(session: Session, owner: Owner) -> Verified:
    """How far the owner of a code got, and whether the code is earned."""
    invite = owner.invite
    progress = labeller_progress(session, labeller_id=owner.labeller_id)
    return Verified(invite.id, owner.labeller_id, owner.labeller, progress.participant,
                    invite.run_id, progress.counted, invite.target_answers, progress.complete,
                    progress.why, progress.earned)


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
    `entry_pass`: `labelqueue.entry_test`; let go without a code). The first of these that came
    with a code is kept (`invitees.completed_why`) and stays the answer from then on, though
    the run be requeued or the pause lifted, and though they label more (`counted` grows)"""
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
    paused: bool = False
    """check pairs left them nothing to label: paused on the invite's run; for an all-runs
    invite, on every run still giving pairs (once none does, on every run they answered on)"""
    active: bool = True
    """the labeller is active: an operator deactivated them otherwise (rejected their work)"""

    @property
    def earned(self) -> bool:
        """the code is earned: the study is complete, not by failing the entry test, the code
        was not withheld (a pause on an invite with a `pause_message`: the participant is told
        to return the study, and shown no code), and the labeller was not deactivated"""
        withheld = self.why == "paused" and self.pause_message is not None
        return self.complete and self.why != "entry_failed" and not withheld and self.active


def labeller_progress(session: Session, *, labeller_id: int) -> Progress:
    """How far the labeller is. For one who joined by an invite: decisive answers on the
    invite's runs against its target (practice answers never count), and whether the study is
    complete for them (target reached, runs over or budget spent, paused by check pairs, or
    nothing left to label after waiting), with their own code; or let go without one, having
    failed the invite's entry test (which comes before every other end). The first completion
    found with a code is kept (`_keep`) and wins over what their runs say later."""
    with reading(session):
        invite = session.scalars(select(Invite).join(Invitee, Invitee.invite_id == Invite.id)
                                 .where(Invitee.labeller_id == labeller_id)).one_or_none()
        if invite is None:
            labels = session.scalar(select(func.count(Label.id)).where(
                Label.labeller_id == labeller_id, *_STANDING)) or 0
        else:
            read = _read(session, invite, labeller_id)
        session.expunge_all()
    if invite is None:
        return Progress(labels, None, None, None, counted=labels)
    return _progress(session, invite, read)[labeller_id]


def study_progress(session: Session, *, invite: Invite) -> dict[int, Progress]:
    """How far each participant of the invite is (`labeller_progress`), by labeller id: read
    in as many statements for a thousand participants as for one."""
    with reading(session):
        read = _read(session, invite, None)
        session.expunge_all()
    return _progress(session, invite, read)


_STANDING = (Label.source == LabelSource.HUMAN, Label.withdrawn_at.is_(None))
"""a standing answer by hand: one not taken back"""


@dataclass(frozen=True)
class _Read:
    """What the progress of an invite's participants is made of, as read in one transaction."""

    people: Sequence[Any]
    """per participant: labeller_id, participant, nothing_left_at, entry_passed,
    entry_correct, completed_why, active"""
    labels: dict[int, int]
    """standing answers by hand on any run, by labeller"""
    counted: dict[int, int]
    """what the target counts, by labeller"""
    paused: set[int]
    """the labellers check pairs left nothing to label (`_paused`)"""
    over: bool
    """the invite's runs are over (`runs_open`)"""


def _read(session: Session, invite: Invite, labeller_id: int | None) -> _Read:
    """The invite's participants (`labeller_id`: that one only) as their progress needs them,
    in a fixed number of statements. Call it inside a transaction."""
    mine = [Invitee.invite_id == invite.id]
    if labeller_id is not None:
        mine.append(Invitee.labeller_id == labeller_id)
    people = session.execute(
        select(Invitee.labeller_id, Invitee.participant, Invitee.nothing_left_at,
               Invitee.entry_passed, Invitee.entry_correct, Invitee.completed_why,
               Labeller.active)
        .join(Labeller, Labeller.id == Invitee.labeller_id).where(*mine)
    ).all()
    # Practice answers never count toward a target (labelqueue.practice).
    on_runs = [Label.run_id == invite.run_id] if invite.run_id is not None else []
    counts = case((and_(Label.answer.in_(DECISIVE), Label.practice.is_(False), *on_runs), 1),
                  else_=0)
    answers = session.execute(
        select(Label.labeller_id, func.count(Label.id), func.sum(counts))
        .join(Invitee, Invitee.labeller_id == Label.labeller_id)
        .where(*mine, *_STANDING).group_by(Label.labeller_id)
    ).all()
    live = live_runs(session, invite.run_id)
    over = not live and not runs_open(session, invite.run_id)
    return _Read(people, {who: total for who, total, _ in answers},
                 {who: int(counted or 0) for who, _, counted in answers},
                 _paused(session, invite, mine, live), over)


def _paused(session: Session, invite: Invite, mine: list[Any], live: list[int]) -> set[int]:
    """The participants (`mine`: the conditions on `Invitee` that pick them) check pairs left
    nothing: paused on the invite's run; for an all-runs invite, on every run still giving pairs
    (`live`), or once none does, on every run they answered on."""
    on: dict[int, set[int]] = {}
    for who, run_id in session.execute(
            select(LabellerPause.labeller_id, LabellerPause.run_id)
            .join(Invitee, Invitee.labeller_id == LabellerPause.labeller_id).where(*mine)):
        on.setdefault(who, set()).add(run_id)
    if invite.run_id is not None:
        return {who for who, runs in on.items() if invite.run_id in runs}
    if live:
        return {who for who, runs in on.items() if set(live) <= runs}
    answered: dict[int, set[int]] = {}
    for who, run_id in session.execute(
            select(Label.labeller_id, Label.run_id).distinct()
            .join(Invitee, Invitee.labeller_id == Label.labeller_id)
            .where(*mine, *_STANDING, Label.practice.is_(False))):
        answered.setdefault(who, set()).add(run_id)
    return {who for who, runs in on.items() if answered.get(who, set()) <= runs}


def _progress(session: Session, invite: Invite, read: _Read) -> dict[int, Progress]:
    """Each participant's progress from what was read; the completions found with a code for
    the first time kept (`_keep`), their codes made with one read of the key."""
    out: dict[int, Progress] = {}
    coded: list[int] = []
    first: dict[int, str] = {}
    for labeller_id, participant, nothing_left, entry_passed, entry_correct, kept, active \
            in read.people:
        counted = read.counted.get(labeller_id, 0)
        paused = labeller_id in read.paused
        reached = invite.target_answers is not None and counted >= invite.target_answers
        failed = entry_passed is not None and not entry_passed
        why = kept or (
            "entry_failed" if failed else "target" if reached else "runs_over" if read.over
            else "paused" if paused else "nothing_left" if nothing_left is not None else None)
        progress = Progress(read.labels.get(labeller_id, 0), invite.target_answers, None,
                            invite.run_id, counted=counted, invited=True,
                            complete=why is not None, why=why, paused=paused, active=active,
                            participant=participant, entry_correct=entry_correct,
                            entry_pass=invite.entry_pass)
        if why == "entry_failed" or (why == "paused" and invite.pause_message):
            # Let go without a code, or told to return the study: the study's own words.
            progress = replace(progress, pause_message=invite.pause_message)
        elif why is not None:
            coded.append(labeller_id)
            if kept is None:  # complete, with a code, for the first time: kept from now on
                first[labeller_id] = why
        out[labeller_id] = progress
    kept_now = _keep(session, first) if first else {}
    key = server_key(session) if coded else b""
    for labeller_id in coded:
        progress = out[labeller_id]
        code = participant_code(key, invite, labeller_id)
        redirect = (completion_redirect(invite.redirect_url, code=code,
                                        participant=progress.participant)
                    if invite.redirect_url else None)
        out[labeller_id] = replace(progress, why=kept_now.get(labeller_id, progress.why),
                                   completion_code=code, redirect_url=redirect)
    return out


def _keep(session: Session, found: dict[int, str]) -> dict[int, str]:
    """Record that each participant's study is complete with a code, for its reason in `found`
    (by labeller id), unless it was already (a request beside this one): the reasons kept,
    first come. One statement per reason, however many participants."""
    with transaction(session):
        for why in set(found.values()):
            changed(session, update(Invitee).where(
                Invitee.labeller_id.in_([who for who, was in found.items() if was == why]),
                Invitee.completed_at.is_(None),
            ).values(completed_at=utcnow(), completed_why=why))
        kept: dict[int, str | None] = {
            who: why for who, why in session.execute(
                select(Invitee.labeller_id, Invitee.completed_why)
                .where(Invitee.labeller_id.in_(list(found))))}
    return {who: kept.get(who) or why for who, why in found.items()}

"""A list to pay from: everyone who joined a study (an invite), with what they did and their
completion code, and the check of many codes at once.

Each participant's row counts their standing answers by hand on the invite's run (on any run
for an all-runs invite): decisive (left or right), equal, can't tell, skips and, of the skips,
flags; practice answers apart (they earn nothing); their gold score (correct of gold answers,
practice left out); whether check pairs paused them (on the invite's run; for an all-runs
invite, on every run still giving pairs); their study's state and their code, valid
once the study is complete for them (`crowdstudy.completion.labeller_progress`), never for one who
failed the invite's entry test (`labelqueue.entry_test`: why "entry_failed", not to be paid),
for one paused where the invite's pause message replaces the code (told to return the study),
nor for one an operator deactivated (`active` false).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from crowdstudy.completion import (
    code_owner,
    code_owners,
    participant_code,
    study_progress,
)
from labelqueue.errors import NotFound
from labelqueue.gold import gold_answer
from labelqueue.keys import server_key
from labelqueue.models import (
    ExternalPair,
    Invite,
    Invitee,
    Label,
    Labeller,
    LabelSource,
    Query,
)
from labelqueue.transaction import reading
from runvocab.answers import Answer


@dataclass(frozen=True)
class Participant:
    """One person of a study, as the operator pays them."""

    participant: str | None
    labeller_id: int
    labeller: str
    joined_at: datetime
    time_on_task_s: float
    """from joining to their last answer or last request for a pair"""
    decisive: int
    """left or right answers"""
    equal: int
    cant_tell: int
    skips: int
    flags: int
    """skips that flagged the pair"""
    practice: int
    """practice answers (they count for nothing)"""
    gold_answers: int
    gold_correct: int
    paused: bool
    """check pairs left them nothing to label (`crowdstudy.completion.Progress.paused`)"""
    counted: int
    """what the target counts: decisive and equal answers on the invite's run"""
    complete: bool
    why: str | None
    completion_code: str
    """their code, whether earned or not"""
    code_valid: bool
    """the code is earned (`crowdstudy.completion.Progress.earned`): their study is complete (a
    paused participant's too, unless the invite's pause message was given instead of the code),
    not by failing the entry test, and their labeller is active"""
    entry_test: str | None = None
    """the invite's entry test: "passed", "failed" (let go: not to be paid) or "undecided";
    none: the invite has no entry test (`labelqueue.entry_test`)"""
    entry_correct: int | None = None
    """practice answers right when the entry test was decided"""
    active: bool = True
    """the labeller is active; a deactivated one (an operator rejected their work) has not
    earned their code"""


def participants(session: Session, *, invite_id: int) -> list[Participant]:
    """Everyone who joined the invite, in the order they joined, in a fixed number of
    statements however many joined (`crowdstudy.completion.study_progress`). NotFound for an
    unknown one."""
    key = server_key(session)
    with reading(session):
        invite = session.get(Invite, invite_id)
        if invite is None:
            raise NotFound(f"invite {invite_id} does not exist")
        people = session.execute(
            select(Invitee, Labeller.name).join(Labeller, Labeller.id == Invitee.labeller_id)
            .where(Invitee.invite_id == invite_id).order_by(Invitee.joined_at, Invitee.labeller_id)
        ).all()
        ids = [invitee.labeller_id for invitee, _ in people]
        on_run = [Label.run_id == invite.run_id] if invite.run_id is not None else []
        labels = session.execute(
            select(Label.labeller_id, Label.answer, Label.flag, Label.practice,
                   Label.answered_at, Query.gold, Query.first_segment_return,
                   Query.second_segment_return, ExternalPair.gold_answer)
            .join(Query, Query.id == Label.query_id)
            .outerjoin(ExternalPair, ExternalPair.query_id == Query.id)
            .where(Label.labeller_id.in_(ids), Label.withdrawn_at.is_(None),
                   Label.source == LabelSource.HUMAN, *on_run)
        ).all() if ids else []
        session.expunge_all()
    progress_of = study_progress(session, invite=invite)
    by_labeller: dict[int, list[Any]] = {}
    for row in labels:
        by_labeller.setdefault(row.labeller_id, []).append(row)
    out = []
    for invitee, name in people:
        rows = by_labeller.get(invitee.labeller_id, [])
        real = [r for r in rows if not r.practice]
        kinds = Counter(r.answer for r in real)
        gold = [r for r in real if r.gold and r.answer != Answer.SKIP]
        correct = sum(r.answer == gold_answer(r.first_segment_return,
                                              r.second_segment_return, r.gold_answer)
                      for r in gold)
        last = max([invitee.joined_at, *(r.answered_at for r in rows),
                    *([invitee.asked_at] if invitee.asked_at else [])])
        progress = progress_of[invitee.labeller_id]
        out.append(Participant(
            participant=invitee.participant, labeller_id=invitee.labeller_id, labeller=name,
            joined_at=invitee.joined_at,
            time_on_task_s=round((last - invitee.joined_at).total_seconds(), 1),
            decisive=kinds[Answer.FIRST] + kinds[Answer.SECOND], equal=kinds[Answer.EQUAL],
            cant_tell=kinds[Answer.CANT_TELL], skips=kinds[Answer.SKIP],
            flags=sum(r.flag is not None for r in real),
            practice=len(rows) - len(real), gold_answers=len(gold), gold_correct=correct,
            paused=progress.paused, counted=progress.counted,
            complete=progress.complete, why=progress.why,
            completion_code=participant_code(key, invite, invitee.labeller_id),
            code_valid=progress.earned,
            entry_test=None if invite.entry_pass is None else "undecided"
            if invitee.entry_passed is None else "passed" if invitee.entry_passed else "failed",
            entry_correct=invitee.entry_correct, active=progress.active,
        ))
    return out


CSV_COLUMNS = ("participant", "labeller_id", "labeller", "joined_at", "time_on_task_s",
               "decisive", "equal", "cant_tell", "skips", "flags", "practice", "gold_answers",
               "gold_correct", "paused", "counted", "complete", "why", "completion_code",
               "code_valid", "entry_test", "entry_correct", "active")


@dataclass(frozen=True)
class CodeCheck:
    """One completion code of a list, checked."""

    code: str
    valid: bool
    """the code is a participant's and earned (`crowdstudy.completion.Progress.earned`), and
    not a `repeat`: pay them"""
    participant: str | None
    labeller_id: int | None
    invite_id: int | None
    why: str | None
    """why their study is complete, or "not_complete", or "unknown" (nobody's code), or
    "other_study" (a participant's of another invite than the one checked for: not valid
    here)"""
    labeller: str | None = None
    run_id: int | None = None
    """the run of their invite; none: all runs (or nobody's code)"""
    counted: int | None = None
    """what the target counts (`crowdstudy.completion.Progress.counted`); none for a code
    not checked ("unknown", "other_study")"""
    target_answers: int | None = None
    repeat: bool = False
    """the same participant's code was given earlier in the list (however written): they are
    paid once, for the first, so this one is not valid"""


def verify_codes(session: Session, codes: Iterable[str], *,
                 invite_id: int | None = None) -> list[CodeCheck]:
    """Each code of a list, in order: whose it is and whether it is earned. Blank lines are
    left out; a participant's code given again (the same, or written otherwise) is a `repeat`,
    never valid: each participant is paid once.
    With `invite_id` (NotFound for an unknown one), a code of another invite's participant is
    "other_study", never valid. Whose each code is is looked up once for the whole list, and
    how far its owner got once for each invite the codes are of (`study_progress`), however
    many codes."""
    if invite_id is not None:
        with reading(session):
            if session.get(Invite, invite_id) is None:
                raise NotFound(f"invite {invite_id} does not exist")
    owners = code_owners(session)
    given = [(code, code_owner(owners, code)) for code in (c.strip() for c in codes) if code]
    studies = {owner.invite.id: owner.invite for _, owner in given
               if owner is not None and invite_id in (None, owner.invite.id)}
    progress_of = {study: study_progress(session, invite=invite)
                   for study, invite in studies.items()}
    out = []
    seen: set[int] = set()
    for code, owner in given:
        if owner is None:
            out.append(CodeCheck(code, False, None, None, None, "unknown"))
            continue
        invite = owner.invite
        # None: a code of another invite than the one checked for
        progress = progress_of[invite.id][owner.labeller_id] if invite.id in studies else None
        why = ("other_study" if progress is None
               else progress.why if progress.complete else "not_complete")
        repeat = owner.labeller_id in seen
        seen.add(owner.labeller_id)
        out.append(CodeCheck(
            code, progress is not None and progress.earned and not repeat, owner.participant,
            owner.labeller_id, invite.id, why, labeller=owner.labeller, run_id=invite.run_id,
            counted=None if progress is None else progress.counted,
            target_answers=None if progress is None else invite.target_answers, repeat=repeat))
    return out

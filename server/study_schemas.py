"""The bodies of a study's list to pay from: its participants, and many codes checked at once
(`labelqueue.participants`)."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import Field

from server.schemas import Body, Out, StudyEnd


class ParticipantOut(Out):
    """One person who joined the study, as the operator pays them."""

    participant: str | None
    """the id the link was opened with (`PROLIFIC_PID`, `workerId`, `participant`)"""
    labeller_id: int
    labeller: str
    joined_at: datetime
    time_on_task_s: float
    """from joining to their last answer or last request for a pair"""
    decisive: int
    """left or right answers (real ones: practice apart)"""
    equal: int
    cant_tell: int
    skips: int
    flags: int
    """skips that flagged the pair as one nobody can judge"""
    practice: int
    """practice answers: they count toward nothing"""
    gold_answers: int
    gold_correct: int
    paused: bool
    """check pairs paused them"""
    counted: int
    """what the target counts: decisive and equal answers on the invite's run"""
    complete: bool
    why: StudyEnd | None
    completion_code: str
    code_valid: bool
    """the code is earned (their study is complete): pay them"""


class CodesRequest(Body):
    codes: list[str] = Field(min_length=1, max_length=2000)
    """completion codes as participants handed them in (blank ones are left out)"""


class CodeCheckOut(Out):
    code: str
    valid: bool
    """a participant's code, and their study is complete"""
    participant: str | None
    labeller_id: int | None
    invite_id: int | None
    why: StudyEnd | Literal["not_complete", "unknown"] | None

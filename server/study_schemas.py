"""A crowd study's bodies: invite links and joining by one, a participant's progress and why
they wait, the list to pay from and many codes checked at once (`crowdstudy.invites`,
`crowdstudy.participants`)."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

from pydantic import BaseModel, Field

from crowdstudy.invites import InviteState
from server.schemas import (
    Body,
    FilledText,
    Out,
    Positive,
)

InviteDays = Annotated[float, Field(ge=1 / 1440, le=366)]
"""days, from a minute to a year"""
StudyEnd = Literal["target", "runs_over", "paused", "nothing_left", "entry_failed"]
"""why a participant's study is complete (`crowdstudy.completion.Progress.why`)"""


REDIRECT_PATTERN = (r"^https?://([A-Za-z0-9._~%!$&'()*+,;=:-]*@)?[A-Za-z0-9._~%!$&'()*+,;=-]+"
                    r"(:[0-9]{0,5})?([/?#][^\s\x00]*)?$")
"""an absolute http(s) URL whose host is a name or an IPv4 address in plain ASCII (no
`{participant}` or `{code}` there), with no white space or NUL character"""


class InviteCreate(Body):
    """A new invite link. Opening it makes a new labeller, until it expires, is used up or is
    revoked."""

    run_id: Positive | None = None
    """the one run its labellers are sent to; null: all runs taught by people"""
    expires_in_days: InviteDays = 7.0
    """how long the link works, from now"""
    max_uses: Positive | None = None
    """labellers it may make; null: no limit"""
    target_answers: Positive | None = None
    """decisive answers (not skips or can't-tells) on the invite's run after which a
    participant's study is complete; null: it completes when the run is over"""
    completion_code: str | None = Field(default=None, min_length=1, max_length=40,
                                        pattern=r"^[A-Za-z0-9_-]+$")
    """the study's code (a platform's): the prefix of every participant's own completion code
    (`<this>-XXXX-XXXX-XXXX`); null: their own part alone"""
    note: FilledText | None = Field(default=None, min_length=1, max_length=200)
    """the operator's own name for the link"""
    redirect_url: str | None = Field(default=None, min_length=1, max_length=2000,
                                     pattern=REDIRECT_PATTERN,
                                     examples=["https://app.prolific.com/submissions/complete"
                                               "?cc=C1234"])
    """where a participant is sent when their study is complete (a platform's completion URL):
    `{code}` and `{participant}` in it are filled in; without either, `participant=<id>` is
    added when the link was opened with one"""
    consent_text: FilledText | None = Field(default=None, min_length=1, max_length=8000)
    """shown on the invite's page: nobody joins without agreeing to it"""
    pause_message: FilledText | None = Field(default=None, min_length=1, max_length=2000)
    """what a participant paused by check pairs is told instead of being given their code (their
    code is then not earned: the message should ask them to return the study)"""
    wait_limit_s: Positive | None = None
    """a participant who asks this long for pairs and gets none finishes with their code
    ("nothing left to label"); null: 300 s"""
    entry_pass: Positive | None = None
    """an entry test: the practice answers a participant must get right, of the run's
    `feedback.practice_pairs`, to go on; one who answers them all with fewer right is let go,
    without a code (and not to be paid). From 1 to the run's practice pairs (a run without
    practice pairs takes none); null: no entry test"""


class InviteOut(Out):
    id: int
    code: str
    url: str
    """the link to hand out (append `?participant=<id>` to name the labeller)"""
    run_id: int | None
    note: str | None
    expires_at: datetime
    max_uses: int | None
    uses: int
    target_answers: int | None
    completion_code: str | None
    """the study's code, the prefix of each participant's own"""
    created_at: datetime
    revoked_at: datetime | None
    redirect_url: str | None
    consent_text: str | None
    pause_message: str | None
    wait_limit_s: int | None
    entry_pass: int | None
    """practice answers to get right to go on; null: no entry test"""
    entry_test_missing: str | None = None
    """why its participants cannot take its entry test now: none of its open runs has
    `entry_pass` practice pairs (an all-runs link), so they are served nothing to label; null:
    nothing is missing, or no entry test"""
    state: InviteState
    """closed: its run is over (stopping, stopped, finished or failed, or its budget spent; for
    an all-runs link, no run taught by people is queued, running or paused with budget left)"""


class JoinRequest(Body):
    participant: str | None = Field(default=None, min_length=1, max_length=64,
                                    pattern=r"^[A-Za-z0-9_.@+-]+$")
    """a name or a crowdsourcing platform's worker id; the labeller is named after it"""
    consent: bool = False
    """the person agreed to the invite's consent text (required when it has one)"""


class JoinedOut(BaseModel):
    """A labeller made by an invite link, with its bearer token: shown this once."""

    labeller_id: int
    name: str
    token: str
    run_id: int | None
    target_answers: int | None
    rejoined: bool = False
    """the participant had joined before: the same labeller (its answers and code), with this
    new token; the browser it joined from before is signed out"""


class ProgressOut(BaseModel):
    """The caller's answers so far and, for one who joined by an invite, where their study
    stands: complete once the target is reached, the run is over (or its budget spent), or
    check pairs paused them, or they waited the invite's limit with nothing to label; then
    their own completion code."""

    labels: int
    """answers given on any run, skips included"""
    target_answers: int | None
    completion_code: str | None
    """the caller's own code, once their study is complete (null before, and for a paused
    participant whose invite gives a message instead)"""
    run_id: int | None
    """the run the caller's invite was for; null: all runs"""
    counted: int = 0
    """what the target counts: decisive answers on the invite's run (`labels` for others)"""
    invited: bool = False
    complete: bool = False
    why: StudyEnd | None = None
    participant: str | None = None
    redirect_url: str | None = None
    """where to go now that the study is complete, filled in for the caller"""
    pause_message: str | None = None
    """the study's words for a participant let go without a code (paused by check pairs, or
    failed the entry test), when it has some"""
    entry_correct: int | None = None
    """practice answers the caller got right, once the invite's entry test is decided"""
    entry_pass: int | None = None
    """the invite's entry test: practice answers to get right; null: none"""


class WaitingOut(BaseModel):
    """Why there is nothing to label now."""

    reason: str
    """the run's phase (`queued`, `starting`, `pretraining`, `exploring`, `training`,
    `labelling`: the rest of the round is with others, `paused`, `silent`, `stopping`),
    `no_run`, or `entry_test`: the caller's entry test waits for a run with practice pairs"""
    text: str
    run_id: int | None
    eta_s: float | None
    """seconds until pairs may come, when known"""


class StatusOut(BaseModel):
    """The label page's look when it has nothing to show: the caller's progress, and why it
    waits (null once the study is complete)."""

    progress: ProgressOut
    waiting: WaitingOut | None


class VerifyRequest(Body):
    code: str = Field(min_length=1, max_length=120)


class VerifiedOut(BaseModel):
    """Whose completion code it is and how far they got."""

    invite_id: int
    labeller_id: int
    labeller: str
    participant: str | None
    run_id: int | None
    counted: int
    """decisive answers on the invite's run"""
    target_answers: int | None
    complete: bool
    why: StudyEnd | None
    earned: bool
    """the code is earned: pay them (as the participants list's `code_valid`). Not for one let
    go by the entry test, one paused where the invite's pause message replaced the code, nor
    one an operator deactivated"""


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
    """check pairs left them nothing to label: paused on the invite's run (for an all-runs
    invite, on every run still giving pairs; once none does, on every run they answered on)"""
    counted: int
    """what the target counts: decisive and equal answers on the invite's run"""
    complete: bool
    why: StudyEnd | None
    completion_code: str
    code_valid: bool
    """the code is earned: pay them. Their study is complete, not by failing the entry test,
    nor by a pause on an invite whose pause message replaces the code, and their labeller is
    active"""
    entry_test: Literal["passed", "failed", "undecided"] | None = None
    """the invite's entry test; failed: let go without a code, not to be paid; null: the
    invite has none"""
    entry_correct: int | None = None
    """practice answers right when the entry test was decided"""
    active: bool = True
    """the labeller is active; a deactivated one (an operator rejected their work) has not
    earned their code"""


class CodesRequest(Body):
    codes: list[str] = Field(min_length=1, max_length=2000)
    """completion codes as participants handed them in (blank ones are left out)"""
    invite_id: Positive | None = None
    """the study (invite) they were handed in for: another invite's participant's code is then
    `other_study`, never valid; null: any invite's"""


class CodeCheckOut(Out):
    code: str
    valid: bool
    """a participant's code, earned (as the participants list's `code_valid`), and not a
    `repeat`"""
    participant: str | None
    labeller_id: int | None
    invite_id: int | None
    why: StudyEnd | Literal["not_complete", "unknown", "other_study"] | None
    """why the study is complete; `not_complete`; `unknown`: nobody's code; `other_study`: a
    participant's code of another invite than `invite_id` of the request (this `invite_id` is
    theirs)"""
    repeat: bool = False
    """the same participant's code was given earlier in the list (however written): pay them
    once, for the first; this one is not valid"""

"""The label API's bodies as a labeller sees them: the next pair, an answer and what the
server stored of it, the practice round's explanation, the run's brief, taking an answer back,
and the labeller's count. They carry no ground truth: no segment or trajectory returns, no
model probability, no selection score."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from runvocab.answers import FLAG_NOTE_MAX, Click, Flag
from server.schemas import (
    Body,
    Out,
    PlainText,
    Positive,
    UTCTime,
)


class PracticeOut(BaseModel):
    index: int
    """1-based: which practice pair this is"""
    of: int
    """the run's practice pairs"""


class PracticeFeedback(PracticeOut):
    """After a practice answer: what the true reward says, as a ratio, never the returns."""

    correct: bool | None
    """the answer agrees with the true reward; null for can't-tell and skip"""
    better: Literal["left", "right", "equal"]
    explanation: str
    entry_test: Literal["passed", "failed"] | None = None
    """the caller's entry test (an invite's `entry_pass`), once decided (the last practice answer
    decides it); null: undecided, or no test"""


class NextQuery(BaseModel):
    """A leased query as a labeller sees it: two clip URLs, and nothing that hints the answer."""

    query_id: int
    run_id: int
    lease_expires_at: datetime
    left_clip_url: str
    right_clip_url: str
    left_is_first: bool
    """the sides this server chose for the labeller: whether the first segment is on the left"""
    segment_length: int
    left_start_step: int | None
    """the step of its episode the left clip starts at (the player shows it); null when the
    clip is no known part of an episode (an external run's upload)"""
    right_start_step: int | None
    practice: PracticeOut | None = None
    """a pair of the labeller's practice round on the run (`feedback.practice_pairs`): its
    answer is explained once given; null for any other pair"""


class LabelSubmit(Body):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"allOf": [
        # A flag goes with a skip only; a note (something besides white space) with a flag.
        {"if": {"properties": {"flag": {"type": "string"}}, "required": ["flag"]},
         "then": {"properties": {"choice": {"const": "skip"}}}},
        {"if": {"properties": {"flag_note": {"type": "string", "pattern": r"\S"}},
                "required": ["flag_note"]},
         "then": {"properties": {"flag": {"type": "string"}}, "required": ["flag"]}},
    ]})

    choice: Click
    """what was clicked; the server turns it into an answer with the sides it chose"""
    left_is_first: bool | None = None
    """optional: the value next-query gave, as a check; a different one is refused (422)"""
    shown_at: UTCTime
    """when the page showed the pair, as an RFC 3339 date-time with its offset (a number is a
    422); stored clamped to [the lease's start, the answer's time]"""
    flag: Flag | None = None
    """the pair is one nobody can judge: clip_broken, not_visible or other; only with choice
    skip (422 otherwise), so it is never trained on"""
    flag_note: PlainText | None = Field(default=None, max_length=FLAG_NOTE_MAX)
    """optional words on the flag"""


class LabelOut(Out):
    id: int
    query_id: int
    run_id: int
    labeller_id: int
    choice: str
    left_is_first: bool
    answer: str
    """the answer in segment terms: first, second, equal, cant_tell or skip"""
    shown_at: datetime | None
    answered_at: datetime
    flag: str | None = None
    """clip_broken, not_visible or other when the labeller flagged the pair"""
    flag_note: str | None = None
    practice_feedback: PracticeFeedback | None = None
    """a practice answer, explained (`feedback.practice_pairs`); null for any other"""


class LabelCount(BaseModel):
    """How many labels the caller has given, over all runs."""

    labels: int


class RunBrief(BaseModel):
    """What the label page shows about the run of the pair on screen."""

    run_id: int
    task: str
    instruction: str
    """what "better" means for this run: the operator's text, or the task's own"""
    instruction_sha256: str
    clip_width: int
    clip_height: int
    fps: float
    """frames per second the clips are encoded at: one frame per environment step"""
    step_seconds: float | None
    """simulated seconds per environment step of the task; null when not known"""
    real_time_ratio: float | None
    """how fast a clip plays at 1x against the task's own time (0.33: a third of real speed)"""


class TakeBack(Body):
    keep: Positive | None = None
    """the query the page shows now: its lease is kept; the caller's other leases are released"""


class TakenBack(BaseModel):
    """An answer taken back: the label as withdrawn, and its query to show again."""

    label_id: int
    withdrawn_at: datetime
    query: NextQuery
    """the pair again, leased to the caller, as next-query describes it"""

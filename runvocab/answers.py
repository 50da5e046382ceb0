"""The answer to a query, in one vocabulary for the trainer, the queue and the export.

A query is a pair of segments, "first" and "second" (the trainer's segment 0 and 1). An answer
names one of them, or says they are equal, or that the labeller cannot tell, or skips. Left and
right exist only on the screen: a click is turned into an answer at the door, with the sides the
server chose, and the label row keeps both the click and the sides.

Several labellers may answer one query; `aggregate` turns their answers into one, and
`trained_answer` says which answers the reward model trains on (the scripted teacher's alone,
when it answered).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from enum import StrEnum


class Answer(StrEnum):
    FIRST = "first"
    """the first segment is better"""
    SECOND = "second"
    """the second segment is better"""
    EQUAL = "equal"
    """both are as good (trained on as a 0.5 target)"""
    CANT_TELL = "cant_tell"
    """kept on record, not trained on"""
    SKIP = "skip"
    """kept on record, not trained on"""


class Flag(StrEnum):
    """Why a labeller flagged a pair as one nobody can judge; a flagged pair is answered with a
    skip, which is kept on record and never trained on."""

    CLIP_BROKEN = "clip_broken"
    """a clip does not play, stops, or shows something wrong"""
    NOT_VISIBLE = "not_visible"
    """the agent is out of the picture, hidden or too small to judge"""
    OTHER = "other"
    """anything else (the note says what)"""


FLAG_TEXT = {Flag.CLIP_BROKEN: "clip broken", Flag.NOT_VISIBLE: "agent not visible",
             Flag.OTHER: "other"}
"""what the label page and the operator pages call each flag"""
FLAG_NOTE_MAX = 500
"""the longest note a flag may carry"""


class Click(StrEnum):
    """What a labeller clicked, in screen terms."""

    LEFT = "left"
    RIGHT = "right"
    EQUAL = "equal"
    CANT_TELL = "cant_tell"
    SKIP = "skip"


DECISIVE = (Answer.FIRST, Answer.SECOND, Answer.EQUAL)
"""the answers a reward model trains on"""


def answer_of_click(click: Click | str, left_is_first: bool) -> Answer:
    """The answer a click gives when the first segment was (or was not) shown on the left."""
    click = Click(click)
    if click is Click.LEFT:
        return Answer.FIRST if left_is_first else Answer.SECOND
    if click is Click.RIGHT:
        return Answer.SECOND if left_is_first else Answer.FIRST
    return Answer(click.value)


def click_of_answer(answer: Answer | str, left_is_first: bool) -> Click:
    """The click that gives `answer` with these sides (a scripted labeller's click)."""
    answer = Answer(answer)
    if answer is Answer.FIRST:
        return Click.LEFT if left_is_first else Click.RIGHT
    if answer is Answer.SECOND:
        return Click.RIGHT if left_is_first else Click.LEFT
    return Click(answer.value)


def aggregate(answers: Iterable[Answer | str]) -> Answer:
    """The one answer several labellers' answers give the reward model.

    Skips are not answers: none but skips gives skip. Otherwise the most frequent decisive
    answer (first, second or equal) decides, unless can't-tell answers are more than half of
    the answers, or two decisive answers tie for the most: then it is can't-tell, which is kept
    on record and not trained on.
    """
    counted = [Answer(a) for a in answers if Answer(a) is not Answer.SKIP]
    if not counted:
        return Answer.SKIP
    if 2 * counted.count(Answer.CANT_TELL) > len(counted):
        return Answer.CANT_TELL
    decisive = Counter(a for a in counted if a in DECISIVE).most_common()
    if not decisive or (len(decisive) > 1 and decisive[0][1] == decisive[1][1]):
        return Answer.CANT_TELL
    return decisive[0][0]


def trained_answer(answers: Sequence[tuple[Answer | str, bool]]) -> Answer:
    """The one answer the reward model trains on, from a query's standing answers, each with
    whether the scripted teacher gave it: the scripted teacher's first answer when it answered
    (its one answer decides the query), else `aggregate` of them all. The trainer takes it so
    (`trainer.queue_hooks._answer`), and the export's `aggregate` column says it."""
    scripted = [answer for answer, by_teacher in answers if by_teacher]
    return aggregate(scripted[:1] or [answer for answer, _ in answers])

"""Gold pairs: known-answer queries mixed into each labeller's stream to measure them.

The worker pushes a few gold pairs per round when the run's `feedback.gold_rate` is above zero:
pairs whose true segment returns differ by far more than the teacher's band, so their answer,
the segment with the larger return, is beyond doubt. Every labeller may answer each gold pair
once (`GOLD_NEEDS_LABELS`). Nothing a labeller sees tells them from the others: the worker puts
them at random places among the round's queries (`trainer.gold_pairs.round_layout`), so their
ids are the round's like any, and renders their clips in that order; a lease serves a gold pair
only in the order the others come in (`labelqueue.queries`: never behind the furthest query the
labeller answered on the run, nor after the next ordinary one), and only when the labeller's
share of gold answers on the run is below the rate, with an offset per answer drawn from a key
the server keeps in the database (`SCHEDULE_KEY`), so knowing the rate, the code and one's own
ids does not tell when the next check is due. Gold answers are never trained on and never count
against the budget.

After each gold answer the labeller's gold accuracy on the run is checked against the run's
`feedback.gold_min_accuracy` (0: off): below it, once they gave `feedback.gold_min_answers`
gold answers, they are paused on the run (`LabellerPause`). A paused labeller's answers stay;
they get no more of the run's queries until an operator lifts the pause, or they take back
(`labelqueue.undo`) the gold answer that paused them and their record, without it, is no longer
below the threshold.
"""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Integer, bindparam, delete, func, insert, select
from sqlalchemy.orm import Session

from labelqueue.errors import QueueError
from labelqueue.models import (
    EXTERNAL_PAIRS,
    LABELS,
    PAUSES,
    QUERIES,
    RUNS,
    LabellerPause,
    utcnow,
)
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.run_config import FEEDBACK, run_feedback
from labelqueue.transaction import reading, transaction
from runvocab.answers import Answer
from runvocab.config import FeedbackConfig

GOLD_NEEDS_LABELS = 1_000_000
"""a gold pair's `needs_labels`: every labeller's answer"""


class Paused(QueueError):
    """The labeller is paused on the run: their gold accuracy fell below its threshold."""


@dataclass(frozen=True)
class GoldSettings:
    """A run's gold settings, from its feedback settings (`labelqueue.run_config.run_feedback`)
    over the defaults."""

    rate: float
    min_accuracy: float
    min_answers: int

    @classmethod
    def of(cls, feedback: Mapping[str, Any]) -> GoldSettings:
        default = FeedbackConfig()
        return cls(float(feedback.get("gold_rate", default.gold_rate)),
                   float(feedback.get("gold_min_accuracy", default.gold_min_accuracy)),
                   int(feedback.get("gold_min_answers", default.gold_min_answers)))


def gold_answer(first_return: float | None, second_return: float | None,
                known: Answer | str | None = None) -> Answer:
    """A gold pair's answer: the one its external client gave (`known`), else the segment with
    the larger true return."""
    if known is not None:
        return Answer(known)
    assert first_return is not None and second_return is not None, "a gold pair without truth"
    return Answer.FIRST if first_return > second_return else Answer.SECOND


SCHEDULE_KEY = "gold-schedule"
"""the server key (`labelqueue.keys`) the offsets of the gold schedule are drawn with"""


def _offset(key: bytes, labeller_id: int, run_id: int, answers: int) -> float:
    """A uniform number in [0, 1), fixed per labeller, run and answer count, that only a
    holder of `key` can work out."""
    message = f"gold:{labeller_id}:{run_id}:{answers}".encode()
    digest = hmac.new(key, message, hashlib.sha256).digest()
    return int.from_bytes(digest[:8], "big") / 2.0**64


def gold_pick(key: bytes, *, labeller_id: int, run_id: int, answers: int, among: int) -> int:
    """Which of `among` gold pairs that may come next the labeller gets (0-based), drawn with
    `key` per labeller, run and answer count: two newcomers' first checks differ."""
    digest = hmac.new(key, f"gold-pick:{labeller_id}:{run_id}:{answers}".encode(),
                      hashlib.sha256).digest()
    return int.from_bytes(digest[:8], "big") % among


_LABELLER = bindparam("labeller", type_=Integer())
_RUN = bindparam("gold_run", type_=Integer())
_SHARE = Prepared(
    select(func.count().label("answers"),
           func.coalesce(func.sum(QUERIES.c.gold.cast(Integer)), 0).label("gold"),
           func.coalesce(func.max(LABELS.c.query_id), 0).label("furthest"))
    .select_from(LABELS.join(QUERIES, QUERIES.c.id == LABELS.c.query_id))
    .where(LABELS.c.labeller_id == _LABELLER, LABELS.c.run_id == _RUN,
           LABELS.c.withdrawn_at.is_(None), LABELS.c.practice.is_(False))
)


@dataclass(frozen=True)
class GoldShare:
    """A labeller's standing answers on a run (the practice round's left out)."""

    answers: int
    gold: int
    """of them, to gold pairs"""
    furthest: int
    """the largest query id among them (0 for none): how far the labeller got in the run"""


def gold_share(connection: DriverConnection, *, labeller_id: int, run_id: int) -> GoldShare:
    [row] = _SHARE.rows(connection, {"labeller": labeller_id, "gold_run": run_id})
    return GoldShare(int(row.answers), int(row.gold), int(row.furthest))


def gold_due(share: GoldShare, *, key: bytes, labeller_id: int, run_id: int,
             rate: float) -> bool:
    """Whether the labeller's next query on the run should be a gold pair: whether their gold
    answers, plus an offset drawn with `key` for this answer, fall short of `rate` of their
    answers and this one (so they stay within one of the rate's share)."""
    if rate <= 0:
        return False
    offset = _offset(key, labeller_id, run_id, share.answers)
    return share.gold + offset < rate * (share.answers + 1)


_GOLD_ANSWERS = Prepared(
    select(LABELS.c.answer, QUERIES.c.first_segment_return, QUERIES.c.second_segment_return,
           EXTERNAL_PAIRS.c.gold_answer)
    .select_from(LABELS.join(QUERIES, QUERIES.c.id == LABELS.c.query_id)
                 .outerjoin(EXTERNAL_PAIRS, EXTERNAL_PAIRS.c.query_id == QUERIES.c.id))
    .where(LABELS.c.labeller_id == _LABELLER, LABELS.c.run_id == _RUN,
           LABELS.c.withdrawn_at.is_(None), QUERIES.c.gold.is_(True),
           LABELS.c.practice.is_(False))  # the practice round is not measured
)


def gold_record(connection: DriverConnection, *, labeller_id: int,
                run_id: int) -> tuple[int, int]:
    """(gold answers, correct ones) of the labeller on the run; skips are not answers."""
    rows = _GOLD_ANSWERS.rows(connection, {"labeller": labeller_id, "gold_run": run_id})
    answered = [row for row in rows if row.answer != Answer.SKIP]
    correct = sum(row.answer == gold_answer(row.first_segment_return, row.second_segment_return,
                                            row.gold_answer) for row in answered)
    return len(answered), correct


_RUN_CONFIG = Prepared(select(RUNS.c.config, FEEDBACK).where(RUNS.c.id == _RUN))
_PAUSED = Prepared(
    select(PAUSES.c.id).where(PAUSES.c.run_id == _RUN, PAUSES.c.labeller_id == _LABELLER)
)
_PAUSE = Prepared(insert(PAUSES).values(
    run_id=_RUN, labeller_id=_LABELLER, gold_answers=bindparam("answers", type_=Integer()),
    gold_correct=bindparam("correct", type_=Integer()),
    paused_at=bindparam("at", type_=PAUSES.c.paused_at.type)))


def pause_if_below(connection: DriverConnection, *, labeller_id: int, run_id: int) -> bool:
    """After a gold answer: pause the labeller on the run when their gold accuracy is below the
    run's threshold; whether they are paused now."""
    params = {"labeller": labeller_id, "gold_run": run_id}
    if _PAUSED.first(connection, params) is not None:
        return True
    settings = GoldSettings.of(run_feedback(_RUN_CONFIG.rows(connection, params)[0]))
    if settings.min_accuracy <= 0:
        return False
    answers, correct = gold_record(connection, labeller_id=labeller_id, run_id=run_id)
    if answers < settings.min_answers or correct >= settings.min_accuracy * answers:
        return False
    _PAUSE.count(connection, params | {"answers": answers, "correct": correct, "at": utcnow()})
    return True


def lift_pause_made_since(session: Session, *, labeller_id: int, run_id: int,
                          since: datetime) -> None:
    """A gold answer given at `since` was taken back: lift the labeller's pause on the run if it
    was made since (by that answer or a later one), then check again what their gold record
    says without it. A pause made before stands: that answer did not cause it."""
    lifted = session.execute(delete(LabellerPause).where(
        LabellerPause.run_id == run_id, LabellerPause.labeller_id == labeller_id,
        LabellerPause.paused_at >= since))
    if getattr(lifted, "rowcount", 0):
        pause_if_below(DriverConnection.under(session.connection()), labeller_id=labeller_id,
                       run_id=run_id)


def pause_notice(answers: int, correct: int, settings: GoldSettings) -> str:
    return (f"paused: {correct} of your {answers} answers on check pairs were right, below the "
            f"{settings.min_accuracy:.0%} this run asks for; an operator can let you go on")


def paused_labellers(session: Session, *, run_id: int) -> list[LabellerPause]:
    """The run's pauses, oldest first."""
    with reading(session):
        pauses = list(session.scalars(select(LabellerPause).where(LabellerPause.run_id == run_id)
                                      .order_by(LabellerPause.id)))
        session.expunge_all()
    return pauses


def lift_pause(session: Session, *, run_id: int, labeller_id: int) -> bool:
    """Let a paused labeller answer the run's queries again; whether a pause was lifted. Their
    gold record is kept: a gold answer that leaves them below the threshold pauses them again."""
    with transaction(session):
        result = session.execute(delete(LabellerPause).where(
            LabellerPause.run_id == run_id, LabellerPause.labeller_id == labeller_id))
    return bool(getattr(result, "rowcount", 0))

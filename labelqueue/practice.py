"""The practice round: a run's `feedback.practice_pairs` gold pairs, served to each labeller
before their first real answer on the run, each explained once answered (which clip the true
reward prefers, and by how much). Practice answers are stored with `labels.practice`, never
trained on (gold answers never are), and left out of the labeller's gold accuracy and of their
share of gold answers (`labelqueue.gold`); the quality table shows them apart.

A labeller is in the practice round while every standing answer they gave on the run is a
practice answer and there are fewer than the run's practice pairs; the lease then serves a gold
pair first whenever one is open to them. With no gold pair open (the worker pushes at least
`practice_pairs` gold pairs a round), a labeller starts on real pairs and the round is over.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Integer, bindparam, func, select
from sqlalchemy.orm import Session

from labelqueue.models import LABELS, QUERIES, RUNS, QueryStatus
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.run_config import FEEDBACK, run_feedback
from labelqueue.transaction import driver_transaction
from runvocab.config import FeedbackConfig

_LABELLER = bindparam("practice_labeller", type_=Integer())
_RUN = bindparam("practice_run", type_=Integer())
_COUNTS = Prepared(
    select(func.count().label("answers"),
           func.coalesce(func.sum(LABELS.c.practice.cast(Integer)), 0).label("practice"))
    .where(LABELS.c.labeller_id == _LABELLER, LABELS.c.run_id == _RUN,
           LABELS.c.withdrawn_at.is_(None))
)
_CONFIG = Prepared(select(RUNS.c.config, FEEDBACK).where(RUNS.c.id == _RUN))
# Gold pairs of the run the labeller holds a lease on (the one shown, the one preloaded), and
# those leased before a given one (gold pairs are served oldest first).
_HELD_WHERE = (QUERIES.c.lease_holder == _LABELLER, QUERIES.c.run_id == _RUN,
               QUERIES.c.gold.is_(True), QUERIES.c.status == QueryStatus.LEASED.value)
_HELD = Prepared(select(func.count()).select_from(QUERIES).where(*_HELD_WHERE))
_HELD_BELOW = Prepared(select(func.count()).select_from(QUERIES).where(
    *_HELD_WHERE, QUERIES.c.id < bindparam("practice_below", type_=Integer())))


def practice_pairs(feedback: Mapping[str, Any]) -> int:
    """The run's practice pairs, from its feedback settings (`run_config.run_feedback`) over
    the default (0)."""
    return int(feedback.get("practice_pairs", FeedbackConfig().practice_pairs))


@dataclass(frozen=True)
class PracticeStep:
    index: int
    """1-based: which practice pair the next gold pair is"""
    of: int
    """the run's practice pairs"""


def practice_step(connection: DriverConnection, *, labeller_id: int, run_id: int,
                  feedback: Mapping[str, Any] | None = None,
                  held: str | int | None = None) -> PracticeStep | None:
    """The practice pair the labeller's next gold pair on the run would be; None once the round
    is over (or the run has none). `feedback`: the run's settings (None: they are read). `held`:
    "all" counts the gold pairs the labeller holds leases on as practice pairs to come (a
    lease), a query id those leased before it (a pair shown); None, none (an answer)."""
    if feedback is None:
        feedback = run_feedback(_CONFIG.rows(connection, {"practice_run": run_id})[0])
    pairs = practice_pairs(feedback)
    if pairs <= 0:
        return None
    params: dict[str, Any] = {"practice_labeller": labeller_id, "practice_run": run_id}
    [(answers, practice)] = _COUNTS.rows(connection, params)
    ahead = 0
    if held == "all":
        ahead = int(_HELD.rows(connection, params)[0][0])
    elif held is not None:
        ahead = int(_HELD_BELOW.rows(connection, params | {"practice_below": held})[0][0])
    if int(answers) != int(practice) or int(practice) + ahead >= pairs:
        return None
    return PracticeStep(index=int(practice) + ahead + 1, of=pairs)


def explain(*, left_return: float, right_return: float) -> tuple[str, str]:
    """(the better side: left, right or equal, a sentence for the labeller) of a practice pair,
    from its true segment returns as the clips were shown. Ratios, never the returns."""
    if left_return == right_return:
        return "equal", "They are equally good: by the task's reward neither clip did better."
    side, other = ("left", "right") if left_return > right_return else ("right", "left")
    hi, lo = max(left_return, right_return), min(left_return, right_return)
    if lo > 0 and hi / lo >= 1.05:
        how = f"it did {hi / lo:.1f}× as well as the {other} one"
    elif lo == 0:
        how = f"it earned reward while the {other} one earned none"
    elif lo < 0 <= hi:
        how = f"it earned reward while the {other} one lost some"
    else:
        how = f"it did clearly better than the {other} one"
    return side, f"The {side} clip is better: by the task's reward {how}."


def practice_progress(session: Session, *, labeller_id: int, run_id: int,
                      shown: int | None = None) -> tuple[int, int, PracticeStep | None]:
    """(the labeller's standing practice answers on the run, the run's practice pairs, the
    practice pair their next gold pair would be, or with `shown`, the practice pair that gold
    pair, leased to them, is)."""
    with driver_transaction(session) as connection:
        [(_, practice)] = _COUNTS.rows(
            connection, {"practice_labeller": labeller_id, "practice_run": run_id})
        feedback = run_feedback(_CONFIG.rows(connection, {"practice_run": run_id})[0])
        step = practice_step(connection, labeller_id=labeller_id, run_id=run_id,
                             feedback=feedback, held=shown)
    return int(practice), practice_pairs(feedback), step

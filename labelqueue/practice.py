"""The practice round: a run's `feedback.practice_pairs` pairs, shown to every newcomer before
their first real answer on the run, each explained once answered (which clip the true reward
prefers, and by how much).

Practice pairs are reserved: the first gold pairs the worker pushes to the run (it pushes at
least `practice_pairs` a round) are marked `queries.practice` as they are stored (`reserve`)
and are the run's practice pairs for good, never check pairs. So:

- a practice pair is never leased to one labeller alone: every newcomer is shown it, at once if
  need be (`next_practice`), so nobody starts on real pairs because others hold the practice;
- a practice answer (`labels.practice`) is never charged to the run's budget, never counts
  toward a study's target or a completion code, never trained on, and left out of gold
  accuracy and the gold share (`labelqueue.gold`);
- taking one back leaves a practice pair: answered again, it is practice again, never a check;
- a gold pair served to measure someone is never one they practised on (practice pairs are
  never served as gold).

A labeller is a newcomer on a run while they have no standing answer there but practice ones;
the lease then serves the run's practice pairs they have not answered, in order, before
anything else of the run. With none rendered yet it serves real pairs (and the labeller gets no
practice later), unless their invite makes the round an entry test: then nothing, until one is
(`labelqueue.entry_test.untested`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import Integer, and_, bindparam, exists, func, or_, select
from sqlalchemy.orm import Session

from labelqueue.models import LABELS, PAUSES, QUERIES, RUNS, QueryStatus, RunStatus, TeacherKind
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.run_config import FEEDBACK, run_feedback
from labelqueue.transaction import reading
from runvocab.config import FeedbackConfig

_LABELLER = bindparam("labeller", type_=Integer())
_SHOWN = bindparam("practice_shown", type_=Integer())


def practice_pairs(feedback: Mapping[str, Any]) -> int:
    """The run's practice pairs, from its feedback settings (`run_config.run_feedback`) over
    the default (0)."""
    return int(feedback.get("practice_pairs", FeedbackConfig().practice_pairs))


def reserve(session: Session, *, run_id: int, specs: Sequence[dict[str, Any]]) -> None:
    """Mark the first gold pairs among `specs` (a push's new rows, in order) as the run's
    practice pairs, until the run has `feedback.practice_pairs` of them. Called inside the
    push's transaction."""
    row = session.execute(select(RUNS.c.config, FEEDBACK).where(RUNS.c.id == run_id)).one()
    wanted = practice_pairs(run_feedback(row))
    if wanted <= 0:
        return
    have = session.scalar(select(func.count()).select_from(QUERIES).where(
        QUERIES.c.run_id == run_id, QUERIES.c.practice.is_(True))) or 0
    for spec in sorted((s for s in specs if s["gold"]), key=lambda s: (s["round"],
                                                                     s["position"])):
        if have >= wanted:
            break
        spec["practice"] = True
        have += 1


def _standing(*where: Any) -> Any:
    return exists().where(LABELS.c.labeller_id == _LABELLER, LABELS.c.withdrawn_at.is_(None),
                          *where)


def _next_practice(*, of_run: bool) -> Prepared:
    """The labeller's next practice pair: the oldest rendered practice pair of a run they are a
    newcomer on (one run, or any taught by people), unanswered by them and not the one shown."""
    practice = QUERIES.alias("practice")
    which = (practice.c.run_id == bindparam("run") if of_run
             else RUNS.c.teacher == TeacherKind.HUMAN)
    return Prepared(
        select(*practice.c)
        .join(RUNS, RUNS.c.id == practice.c.run_id)
        .where(
            practice.c.gold.is_(True), practice.c.practice.is_(True), which,
            # Spelled out: an IN list is rendered anew at each execution (`queries.one_of`).
            or_(practice.c.status == QueryStatus.PENDING, practice.c.status == QueryStatus.LEASED),
            practice.c.first_clip.is_not(None), practice.c.second_clip.is_not(None),
            or_(RUNS.c.status == RunStatus.RUNNING, RUNS.c.status == RunStatus.PAUSED),
            practice.c.id != _SHOWN,
            ~_standing(LABELS.c.query_id == practice.c.id),
            ~_standing(LABELS.c.run_id == practice.c.run_id, LABELS.c.practice.is_(False)),
            ~exists().where(PAUSES.c.run_id == practice.c.run_id,
                            PAUSES.c.labeller_id == _LABELLER),
        )
        .order_by(practice.c.id)
        .limit(1)
    )


_NEXT_OF_RUN = _next_practice(of_run=True)
_NEXT_OF_ANY_HUMAN_RUN = _next_practice(of_run=False)


def next_practice(connection: DriverConnection, params: dict[str, Any], *,
                  shown: int | None, until: datetime) -> dict[str, Any] | None:
    """The practice pair to show the labeller next (`params`: the lease's `labeller` and
    `run`), as a query row leased to them until `until`; None when they are no newcomer, or
    have answered every practice pair. The row in the database is not leased: others see it
    too."""
    statement = _NEXT_OF_ANY_HUMAN_RUN if params["run"] is None else _NEXT_OF_RUN
    row = statement.first(connection, params | {"practice_shown": shown or 0})
    if row is None:
        return None
    leased: dict[str, Any] = row._asdict()
    return leased | {"status": QueryStatus.LEASED, "lease_holder": params["labeller"],
                            "leased_at": params["at"], "lease_expires_at": until}


_OPEN_PRACTICE = Prepared(
    select(QUERIES.c.id).where(
        QUERIES.c.id == _SHOWN, QUERIES.c.practice.is_(True),
        or_(QUERIES.c.status == QueryStatus.PENDING, QUERIES.c.status == QueryStatus.LEASED))
)


def shows_practice(connection: DriverConnection, query_id: int) -> bool:
    """Whether `query_id` is an open practice pair (a page showing it has something to label)."""
    return _OPEN_PRACTICE.first(connection, {"practice_shown": query_id}) is not None


@dataclass(frozen=True)
class PracticeStep:
    index: int
    """1-based: which practice pair this is"""
    of: int
    """the run's practice pairs"""


def practice_step(session: Session, *, run_id: int, query_id: int) -> PracticeStep:
    """Which of the run's practice pairs this one is."""
    with reading(session):
        ids = list(session.scalars(select(QUERIES.c.id).where(
            QUERIES.c.run_id == run_id, QUERIES.c.practice.is_(True)).order_by(QUERIES.c.id)))
    return PracticeStep(index=ids.index(query_id) + 1 if query_id in ids else len(ids),
                        of=len(ids))


def practice_answered(session: Session, *, labeller_id: int, run_id: int) -> int:
    """The labeller's standing practice answers on the run."""
    with reading(session):
        return int(session.scalar(select(func.count()).select_from(LABELS).where(
            and_(LABELS.c.labeller_id == labeller_id, LABELS.c.run_id == run_id,
                 LABELS.c.practice.is_(True), LABELS.c.withdrawn_at.is_(None)))) or 0)


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

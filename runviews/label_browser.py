"""The operators' label browser: stored labels, newest first, filtered by run, labeller,
correctness against the hidden truth, flag and gold; one label with its query's truth.

Correct means what the export's `correct` column means (`export.correct_answer`): the answer
names the segment with the larger true segment return, or says equal when the returns are
exactly equal. Only first, second and equal can be correct or not: can't-tell and skip are
neither, and a filter on correctness leaves them out. Labels taken back (undo) are listed only
when asked for (`withdrawn=True`). Pages go by id: `before` the last id of the page before.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

from sqlalchemy import ColumnElement, Select, and_, case, func, or_, select
from sqlalchemy.orm import Session

from labelqueue.errors import Invalid, NotFound
from labelqueue.export import correct_answer
from labelqueue.models import Label, Labeller, Query, Run
from labelqueue.transaction import reading

MAX_PAGE = 200
"""the most labels one page lists"""


def _correct() -> ColumnElement[bool]:
    first, second = Query.first_segment_return, Query.second_segment_return
    return or_(and_(Label.answer == "first", first > second),
               and_(Label.answer == "second", second > first),
               and_(Label.answer == "equal", first == second))


_DECISIVE = Label.answer.in_(("first", "second", "equal"))


@dataclass(frozen=True)
class BrowsedLabel:
    label_id: int
    query_id: int
    run_id: int
    run_name: str
    task: str
    labeller_id: int
    labeller_name: str
    choice: str
    """what was clicked: left, right, equal, cant_tell or skip"""
    answer: str
    """in segment terms: first, second, equal, cant_tell or skip"""
    left_is_first: bool
    correct: bool | None
    """against the true segment returns; none for can't-tell and skip"""
    shadow_choice: str | None
    """the scripted teacher's hidden answer to the query"""
    gold: bool
    flag: str | None
    flag_note: str | None
    answered_at: datetime
    withdrawn: bool


@dataclass(frozen=True)
class LabelPage:
    labels: list[BrowsedLabel]
    matching: int
    """labels that match the filters, on every page"""
    next_before: int | None
    """`before` for the next (older) page; none on the last"""


@dataclass(frozen=True)
class LabelDetail:
    label: BrowsedLabel
    segment_length: int
    round: int
    first_start: int
    second_start: int
    first_trajectory: int
    second_trajectory: int
    first_segment_return: float | None
    second_segment_return: float | None
    true_answer: str | None
    """first, second or equal: what the true segment returns call for"""
    model_p: float | None
    """the reward model's P[second preferred] when the pair was selected"""
    shown_at: datetime | None
    has_clips: bool


def _columns() -> tuple[Any, ...]:
    return (Label.id, Label.query_id, Label.run_id, Run.name, Run.task, Label.labeller_id,
            Labeller.name, Label.choice, Label.answer, Label.left_is_first,
            case((_DECISIVE, _correct()), else_=None), Query.shadow_choice, Query.gold,
            Label.flag, Label.flag_note, Label.answered_at, Label.withdrawn_at.is_not(None))


def _browsed(row: tuple[Any, ...]) -> BrowsedLabel:
    def value(x: object) -> str | None:
        return None if x is None else str(getattr(x, "value", x))

    return BrowsedLabel(
        label_id=row[0], query_id=row[1], run_id=row[2], run_name=row[3], task=row[4],
        labeller_id=row[5], labeller_name=row[6], choice=value(row[7]) or "",
        answer=value(row[8]) or "", left_is_first=bool(row[9]),
        correct=None if row[10] is None else bool(row[10]), shadow_choice=value(row[11]),
        gold=bool(row[12]), flag=value(row[13]), flag_note=row[14], answered_at=row[15],
        withdrawn=bool(row[16]))


def _joined(*columns: Any) -> Select[Any]:
    return (select(*columns).select_from(Label)
            .join(Query, Query.id == Label.query_id)
            .join(Run, Run.id == Label.run_id)
            .join(Labeller, Labeller.id == Label.labeller_id))


def browse_labels(
    session: Session,
    *,
    run_id: int | None = None,
    labeller_id: int | None = None,
    correct: bool | None = None,
    flagged: bool | None = None,
    gold: bool | None = None,
    withdrawn: bool = False,
    before: int | None = None,
    limit: int = 50,
) -> LabelPage:
    """A page of stored labels, newest first, that match every filter given (None: any)."""
    if not 1 <= limit <= MAX_PAGE:
        raise Invalid(f"limit must be between 1 and {MAX_PAGE}, got {limit}")
    where: list[ColumnElement[bool]] = []
    if run_id is not None:
        where.append(Label.run_id == run_id)
    if labeller_id is not None:
        where.append(Label.labeller_id == labeller_id)
    if correct is not None:
        where += [_DECISIVE, _correct() if correct else ~_correct()]
    if flagged is not None:
        where.append(Label.flag.is_not(None) if flagged else Label.flag.is_(None))
    if gold is not None:
        where.append(Query.gold.is_(gold))
    if not withdrawn:
        where.append(Label.withdrawn_at.is_(None))
    with reading(session):
        if run_id is not None and session.get(Run, run_id) is None:
            raise NotFound(f"run {run_id} does not exist")
        if labeller_id is not None and session.get(Labeller, labeller_id) is None:
            raise NotFound(f"labeller {labeller_id} does not exist")
        matching = session.scalar(_joined(func.count()).where(*where))
        page = [] if before is not None and before <= 1 else session.execute(
            _joined(*_columns())
            .where(*where, *([Label.id < before] if before is not None else []))
            .order_by(Label.id.desc()).limit(limit + 1)).all()
    labels = [_browsed(tuple(row)) for row in page[:limit]]
    more = len(page) > limit
    return LabelPage(labels=labels, matching=int(matching or 0),
                     next_before=labels[-1].label_id if more else None)


def label_detail(session: Session, *, label_id: int) -> LabelDetail:
    """One label with what its query holds: where the segments start, their true returns,
    the answer they call for and the model's P at selection."""
    with reading(session):
        row = session.execute(_joined(
            *_columns(), Query.segment_length, Query.round, Query.first_start,
            Query.second_start, Query.first_trajectory, Query.second_trajectory,
            Query.first_segment_return, Query.second_segment_return, Query.model_p,
            Label.shown_at, Query.first_clip, Query.second_clip,
        ).where(Label.id == label_id)).first()
    if row is None:
        raise NotFound(f"label {label_id} does not exist")
    extra = tuple(row)[len(_columns()):]
    (length, round_, start0, start1, traj0, traj1, ret0, ret1, model_p, shown_at,
     clip0, clip1) = extra
    return LabelDetail(
        label=_browsed(tuple(row)[:len(_columns())]), segment_length=length, round=round_,
        first_start=start0, second_start=start1, first_trajectory=traj0,
        second_trajectory=traj1, first_segment_return=ret0, second_segment_return=ret1,
        true_answer=correct_answer(ret0, ret1), model_p=model_p, shown_at=shown_at,
        has_clips=bool(clip0 and clip1))

"""The answers feed: an external run's answers and withdrawals after a cursor, each with its
pair's standing answers and their tally (`answers_after`); and where pairs named by their keys
stand now (`pair_states`), for a reader that needs no event to know a pair is answered."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from externalruns.runs import stored_id
from labelqueue.errors import Invalid
from labelqueue.models import (
    EXTERNAL_PAIRS,
    QUERIES,
    ExternalPair,
    Label,
    Labeller,
    Query,
    QueryStatus,
    Run,
    Withdrawal,
)
from labelqueue.transaction import get_row, reading
from runvocab.answers import DECISIVE, Answer, aggregate

FEED_LIMIT = 500
"""the most events one read of the answers feed returns"""
STATES_LIMIT = 100
"""the most keys one read of pair states names"""

@dataclass(frozen=True)
class Cursor:
    """Where a reader of a run's answers feed is: after this label id and this withdrawal id
    of this run. Written '<run>.<label>.<withdrawal>'; '0.0' is the start of any run's."""

    run: int = 0
    """the run whose feed gave it; 0: the start, of any run"""
    label: int = 0
    withdrawal: int = 0

    def __str__(self) -> str:
        return "0.0" if self == Cursor() else f"{self.run}.{self.label}.{self.withdrawal}"

    @classmethod
    def parse(cls, text: str) -> Cursor:
        """Invalid for text that is no cursor the feed gave: one of three numbers naming run 0
        (read as the start of any run's, it skipped the answers below its ids), or one of two
        numbers (the older form, naming no run) other than the start."""
        parts = text.split(".")
        ids = [stored_id(part) for part in parts]
        if len(parts) == 2 and ids[0] is not None and ids[1] is not None and ids != [0, 0]:
            raise Invalid(f"cursor {text!r} names no run (the feed gives '<run>.<label>."
                          "<withdrawal>'): read from the start, after=0.0, and pass over the "
                          "answers already handled by their label_id")
        if len(parts) == 3 and ids[0] == 0:
            raise Invalid(f"cursor {text!r} names run 0, which is no run: the feed gives "
                          "'<run>.<label>.<withdrawal>', the run's id first (like '7.57.2'), "
                          "or '0.0' for the start")
        if not (len(parts) in (2, 3) and all(i is not None for i in ids)):
            raise Invalid(f"cursor {text[:40]!r} is not one the answers feed gave (like "
                          "'0.0', the start, or '7.57.2')")
        return cls(*(id_ or 0 for id_ in ids)) if len(parts) == 3 else cls()


def tally(answers: Sequence[Answer]) -> tuple[Answer, bool]:
    """The aggregate of a pair's answers (`runvocab.answers.aggregate`: the majority, can't-tell
    when most cannot tell), and whether two decisive answers tie for the most (then can't-tell
    too)."""
    counts = Counter(a for a in answers if a in DECISIVE).most_common()
    tie = len(counts) > 1 and counts[0][1] == counts[1][1]
    return aggregate(answers), tie


@dataclass(frozen=True)
class Feed:
    events: list[dict[str, Any]]
    cursor: Cursor
    open_pairs: int
    """ordinary pairs still short of their k answers"""
    status: str


def answers_after(session: Session, *, run_id: int, cursor: Cursor,
                  limit: int = FEED_LIMIT) -> Feed:
    """The external run's answers and withdrawals after `cursor`, oldest first, each with its
    pair's key and hidden metadata, the pair's standing answers by labeller, their aggregate
    and whether it ties. A label taken back before it was read is never given; one read and
    then taken back comes again as a withdrawal. Practice answers are not given.

    The cursor is exact, with nothing held back: a run's labels (and its withdrawals) commit
    in the order of their ids, since each draws its id holding the run's row lock
    (`labelqueue.labels`, `labelqueue.undo`; SQLite's one writer anyway), so a read that sees
    one sees every one before it. Invalid for another run's cursor or one ahead of the run's
    answers; NotFound for an unknown run."""
    with reading(session):
        status = get_row(session, Run, run_id).status.value
        open_pairs = session.scalar(select(func.count()).select_from(QUERIES).where(
            QUERIES.c.run_id == run_id, QUERIES.c.gold.is_(False),
            QUERIES.c.status.in_((QueryStatus.PENDING, QueryStatus.LEASED)))) or 0
        last_label = session.scalar(select(func.coalesce(func.max(Label.id), 0))
                                    .where(Label.run_id == run_id)) or 0
        last_withdrawal = session.scalar(select(func.coalesce(func.max(Withdrawal.id), 0))
                                         .where(Withdrawal.run_id == run_id)) or 0
        if cursor.run not in (0, run_id):
            raise Invalid(f"cursor {cursor} is run {cursor.run}'s, not run {run_id}'s: read "
                          f"run {run_id}'s answers from the start, after=0.0")
        if cursor.label > last_label or cursor.withdrawal > last_withdrawal:
            raise Invalid(f"cursor {cursor} is ahead of run {run_id}'s answers (its newest "
                             f"is {last_label}.{last_withdrawal})")
        labels = session.execute(
            select(Label, Labeller.name).join(Labeller, Labeller.id == Label.labeller_id)
            .where(Label.run_id == run_id, Label.id > cursor.label,
                   Label.practice.is_(False))
            .order_by(Label.id).limit(limit)).all()
        label_to = labels[-1][0].id if len(labels) == limit else max(
            [cursor.label, *(label.id for label, _ in labels)])
        withdrawals = session.execute(
            select(Withdrawal, Label, Labeller.name)
            .join(Label, Label.id == Withdrawal.label_id)
            .join(Labeller, Labeller.id == Label.labeller_id)
            .where(Withdrawal.run_id == run_id, Withdrawal.id > cursor.withdrawal,
                   Label.practice.is_(False))
            .order_by(Withdrawal.id).limit(limit)).all()
        withdrawal_to = max([cursor.withdrawal, *(w.id for w, _, _ in withdrawals)])
        touched = {label.query_id for label, _ in labels} | {
            label.query_id for _, label, _ in withdrawals}
        state = _pair_states(session, touched)
    events: list[dict[str, Any]] = []
    given = set()
    for label, name in labels:
        if label.withdrawn_at is not None:
            continue  # taken back before anyone read it
        given.add(label.id)
        events.append({"kind": "answer", "label_id": label.id, "labeller_id": label.labeller_id,
                       "labeller": name, "answer": label.answer.value,
                       "at": label.answered_at.isoformat(),
                       "flag": None if label.flag is None else label.flag.value,
                       **state[label.query_id]})
    for withdrawal, label, name in withdrawals:
        if label.id > cursor.label and label.id not in given:
            continue  # its answer was never given (read as taken back): nor is its withdrawal
        events.append({"kind": "withdrawal", "label_id": label.id,
                       "labeller_id": label.labeller_id, "labeller": name,
                       "answer": label.answer.value, "at": withdrawal.withdrawn_at.isoformat(),
                       "flag": None, **state[label.query_id]})
    events.sort(key=lambda event: event["at"])
    return Feed(events=events, cursor=Cursor(run_id, label_to, withdrawal_to),
                open_pairs=open_pairs, status=status)


def pair_states(session: Session, *, run_id: int,
                keys: Sequence[str]) -> tuple[list[dict[str, Any]], list[str]]:
    """The external run's pairs under these keys as they stand now, each as an answers event
    carries it (standing answers, aggregate, tie, complete, withdrawn), in the order of `keys`;
    and the keys no pair of the run has. A reader that read past a pair's answers (before a
    restart, or for another wait) learns here that it has them. NotFound for an unknown run."""
    keys = list(dict.fromkeys(keys))
    with reading(session):
        get_row(session, Run, run_id)
        ids = dict(session.execute(
            select(EXTERNAL_PAIRS.c.key, EXTERNAL_PAIRS.c.query_id)
            .where(EXTERNAL_PAIRS.c.run_id == run_id, EXTERNAL_PAIRS.c.key.in_(keys)))
            .tuples().all())
        state = _pair_states(session, set(ids.values()))
    return [state[ids[key]] for key in keys if key in ids], [k for k in keys if k not in ids]


def _pair_states(session: Session, query_ids: set[int]) -> dict[int, dict[str, Any]]:
    """Per query: its key, meta, gold, k, its standing answers with their tally, and whether
    its client withdrew it (`externalruns.pairs.withdraw_pair`)."""
    if not query_ids:
        return {}
    pairs = session.execute(
        select(Query.id, Query.needs_labels, Query.gold, Query.status, ExternalPair.key,
               ExternalPair.meta)
        .outerjoin(ExternalPair, ExternalPair.query_id == Query.id)
        .where(Query.id.in_(query_ids))).all()
    standing = session.execute(
        select(Label.query_id, Label.labeller_id, Labeller.name, Label.answer)
        .join(Labeller, Labeller.id == Label.labeller_id)
        .where(Label.query_id.in_(query_ids), Label.withdrawn_at.is_(None),
               Label.practice.is_(False))
        .order_by(Label.id)).all()
    answers: dict[int, list[Any]] = {}
    for row in standing:
        answers.setdefault(row.query_id, []).append(row)
    out = {}
    for pair in pairs:
        given = answers.get(pair.id, [])
        agreed, tie = tally([Answer(row.answer) for row in given])
        out[pair.id] = {
            "query_id": pair.id, "key": pair.key, "meta": pair.meta, "gold": pair.gold,
            "k": None if pair.gold else pair.needs_labels,
            "answers": [{"labeller_id": row.labeller_id, "labeller": row.name,
                         "answer": Answer(row.answer).value} for row in given],
            "aggregate": agreed.value if given else None, "tie": tie,
            "complete": not pair.gold and len(given) >= pair.needs_labels,
            "withdrawn": pair.status == QueryStatus.CANCELLED}
    return out

"""Taking an answer back: for `UNDO_SECONDS` after answering, and only while the trainer has not
taken the answer, a labeller may withdraw it; the query is leased to that labeller again (a
practice pair, leased to nobody, is simply shown again: answered again, it is still practice,
never a check pair; none is taken back where the labeller's invite makes the practice round an
entry test).

The label is not deleted: it stays with its `withdrawn_at`, so the export shows what was
answered and taken back. The trainer's reads (`consume_labels`, `labels_for_queries`) skip
withdrawn labels, and the labeller may answer the query again (one standing answer per labeller
and query). The query gets its label count back, the run its budget; a gold answer taken back
lifts the pause it caused, unless the labeller's gold record is still below the run's threshold
without it (`labelqueue.gold`).

Who wins between an undo and the trainer: the worker uses a person's label only once it is
older than `SETTLE_SECONDS` (the undo window and a margin for the two hosts' clocks), and an
undo is refused once the label is older than the window, taken by the trainer, or its round
closed: the worker closes a round with `cancel_queries`, which withdraws its open queries and
marks the answers they have taken, before it reads them.
"""

from __future__ import annotations

import hmac
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session

from labelqueue.errors import Conflict, NotFound, Revoked, RunClosed, StaleToken
from labelqueue.gold import lift_pause_made_since
from labelqueue.models import (
    Invite,
    Invitee,
    Label,
    Labeller,
    Query,
    QueryStatus,
    Run,
    Withdrawal,
    utcnow,
)
from labelqueue.queries import LABELLABLE, LEASE_SECONDS
from labelqueue.transaction import changed, detach, get_row, transaction

UNDO_SECONDS = 10.0
"""how long after answering a labeller may take the answer back"""
SETTLE_SECONDS = UNDO_SECONDS + 5.0
"""how old a person's label must be before the trainer uses it"""


class UndoRefused(Conflict):
    """The answer can no longer be taken back: too late, the trainer took it, or its round
    closed."""


@dataclass(frozen=True)
class Withdrawn:
    """A label taken back, and its query leased to the labeller again."""

    label: Label
    query: Query


def withdraw_label(
    session: Session,
    *,
    query_id: int,
    labeller_id: int,
    keep: int | None = None,
    lease_seconds: float = LEASE_SECONDS,
    window_seconds: float = UNDO_SECONDS,
    token_hash: str | None = None,
) -> Withdrawn:
    """Take back the labeller's standing answer to the query and lease the query to it again;
    the labeller's other leases are released, but `keep`'s (the pair it is looking at now).

    NotFound when it has no standing answer to the query; UndoRefused when the answer is older
    than `window_seconds`, the trainer has taken it or its round has closed (a check or practice
    answer, never the trainer's, says the latter), or it is a practice answer of a labeller
    whose invite makes the practice round an entry test (`labelqueue.entry_test`: the test
    measures the first try, not one made after the explanation); RunClosed when the run takes
    no answers; Conflict when the pair has been cancelled or another labeller holds it now. On
    refusal nothing changes. A deactivated labeller takes nothing back (Revoked), and given
    `token_hash` (the hash of the bearer token a person asks with), nor one whose token was
    replaced (StaleToken): both read in this transaction, so they hold at once from any process.
    """
    now = utcnow()
    with transaction(session):
        labeller = get_row(session, Labeller, labeller_id)
        if not labeller.active:
            raise Revoked(f"labeller {labeller_id} is deactivated")
        if token_hash is not None and not hmac.compare_digest(labeller.token_hash, token_hash):
            raise StaleToken(f"labeller {labeller_id}'s token was replaced by a new one")
        label = session.scalars(
            select(Label)
            .where(Label.query_id == query_id, Label.labeller_id == labeller_id,
                   Label.withdrawn_at.is_(None))
            .execution_options(populate_existing=True)
        ).one_or_none()
        if label is None:
            raise NotFound(f"labeller {labeller_id} has no answer to query {query_id} to take "
                           "back")
        if label.practice and session.scalar(select(Invite.entry_pass).join(
                Invitee, Invitee.invite_id == Invite.id).where(
                Invitee.labeller_id == labeller_id)) is not None:
            raise UndoRefused("this study's practice answers are its entry test: a practice "
                              "answer cannot be taken back")
        age = (now - label.answered_at).total_seconds()
        query = get_row(session, Query, query_id)
        if label.consumed_at is not None:
            raise _sealed(query, "already")
        if age > window_seconds:
            raise UndoRefused(f"that answer was given {age:.0f} s ago: answers can be taken "
                              f"back for {window_seconds:.0f} s only")
        withdrawn = changed(
            session,
            update(Label)
            .where(Label.id == label.id, Label.withdrawn_at.is_(None),
                   Label.consumed_at.is_(None))
            .values(withdrawn_at=now),
        )
        if not withdrawn:  # the trainer took it, or its round closed, meanwhile (PostgreSQL)
            raise _sealed(query, "just")
        run = get_row(session, Run, label.run_id)
        if run.status not in LABELLABLE:
            raise RunClosed(f"run {run.id} is {run.status}: it takes no more answers, so the "
                            "answer stands")
        query = get_row(session, Query, query_id)
        if query.practice:  # shown to everyone at once, leased to nobody: it stays practice
            if query.status is QueryStatus.CANCELLED:
                raise Conflict(f"query {query_id} was cancelled: the answer stands")
        else:
            _lease_again(session, query_id=query_id, labeller_id=labeller_id, now=now,
                         lease_seconds=lease_seconds)
        # The labeller's other leases go back before the run's row is locked: queries first,
        # then the run, as a submit takes them, so that an undo and a submit of the same
        # labeller cannot wait for each other (a deadlock on PostgreSQL).
        changed(
            session,
            update(Query)
            .where(Query.lease_holder == labeller_id, Query.status == QueryStatus.LEASED,
                   Query.id != query_id, Query.id != (keep or 0))
            .values(status=QueryStatus.PENDING, lease_holder=None, lease_expires_at=None,
                    leased_at=None),
        )
        if not query.practice:
            # A gold pair's answer never counted against the budget (labelqueue.gold).
            if not query.gold:
                changed(session, update(Run).where(Run.id == run.id)
                        .values(labels_used=Run.labels_used - 1))
            elif session.get_bind().dialect.name == "postgresql":  # the run's lock all the same
                session.execute(select(Run.id).where(Run.id == run.id).with_for_update())
        # Drawn while this transaction holds the run's row lock (taken after the queries', as a
        # submit takes them), a run's withdrawals commit in the order of their ids, as its
        # labels do: the answers feed's cursor misses none (`externalruns.feed`).
        session.add(Withdrawal(label_id=label.id, run_id=run.id, withdrawn_at=now))
        session.flush()
        if query.gold and not query.practice:  # the answer may be what paused the labeller
            lift_pause_made_since(session, labeller_id=labeller_id, run_id=run.id,
                                  since=label.answered_at)
        label = get_row(session, Label, label.id)
        query = get_row(session, Query, query_id)
        detach(session, label, query)
    if query.practice:  # shown again as a lease would show it
        query.status, query.lease_holder = QueryStatus.LEASED, labeller_id
        query.leased_at, query.lease_expires_at = now, now + timedelta(seconds=lease_seconds)
    return Withdrawn(label=label, query=query)


def _sealed(query: Query, when: str) -> UndoRefused:
    """The refusal of an answer sealed `when` ("already", "just"): the trainer takes ordinary
    answers as a round closes, but never a check or practice answer: the close sealed that."""
    if query.gold:
        return UndoRefused(f"the round that answer was given in has {when} closed: it can no "
                           "longer be taken back")
    return UndoRefused(f"the trainer has {when} taken that answer (its round has closed): it "
                       "can no longer be taken back")


def _lease_again(session: Session, *, query_id: int, labeller_id: int, now: datetime,
                 lease_seconds: float) -> None:
    """Give the query its answer back and lease it to the labeller again; Conflict when its
    round was cancelled or another labeller holds it now."""
    leased = changed(
        session,
        update(Query)
        .where(
            Query.id == query_id,
            or_(
                Query.status.in_((QueryStatus.LABELLED, QueryStatus.PENDING)),
                and_(Query.status == QueryStatus.LEASED,
                     or_(Query.lease_holder == labeller_id, Query.lease_expires_at <= now)),
            ),
        )
        .values(
            label_count=Query.label_count - 1,
            status=QueryStatus.LEASED,
            lease_holder=labeller_id,
            lease_expires_at=now + timedelta(seconds=lease_seconds),
            leased_at=now,
        ),
    )
    if not leased:
        query = get_row(session, Query, query_id)
        raise Conflict(
            f"query {query_id} was cancelled when its round closed: the answer stands"
            if query.status is QueryStatus.CANCELLED
            else f"another labeller is answering query {query_id} now: the answer stands"
        )


def settled(answered_at: datetime, now: datetime | None = None) -> bool:
    """Whether a label answered then can no longer be taken back (the trainer may use it)."""
    return ((now or utcnow()) - answered_at).total_seconds() >= SETTLE_SECONDS

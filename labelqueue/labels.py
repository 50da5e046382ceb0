"""Labels: a labeller's answer to a leased query, and the trainer taking the answers.

Taking labels safely: `consume_labels` marks labels consumed in the same transaction that
returns them, so a consumer that dies before the commit loses nothing and two consumers never
get the same label. A trainer that dies after the commit but before its next checkpoint resumes
from that checkpoint, which holds the ids of its open round's queries; `labels_for_queries`
returns their labels whether consumed or not, so nothing taken after the checkpoint is lost.
"""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime

from sqlalchemy import ColumnElement, case, select, update
from sqlalchemy.orm import Session

from labelqueue.errors import LeaseError, NotFound, Revoked, RunClosed
from labelqueue.models import (
    Choice,
    Label,
    Labeller,
    LabelSource,
    Preferred,
    Query,
    QueryStatus,
    Run,
    utcnow,
)
from labelqueue.queries import LABELLABLE
from labelqueue.transaction import changed, detach, get_row, transaction


def preferred_segment(choice: Choice | str, left_is_first: bool) -> Preferred | None:
    """The answer in segment terms: first, second or equal; None for cant_tell and skip."""
    choice = Choice(choice)
    if choice is Choice.EQUAL:
        return Preferred.EQUAL
    if choice in (Choice.LEFT, Choice.RIGHT):
        return Preferred.FIRST if (choice is Choice.LEFT) == left_is_first else Preferred.SECOND
    return None


def _stored_label(session: Session, *, query_id: int, labeller_id: int) -> Label | None:
    return session.scalars(
        select(Label)
        .where(Label.query_id == query_id, Label.labeller_id == labeller_id)
        .execution_options(populate_existing=True)
    ).one_or_none()


def _why_no_lease(query: Query, *, labeller_id: int, now: datetime) -> str:
    if query.status in (QueryStatus.LABELLED, QueryStatus.CANCELLED):
        return f"query {query.id} is {query.status}"
    if query.status is QueryStatus.LEASED and query.lease_holder == labeller_id:
        return f"labeller {labeller_id}'s lease on query {query.id} has expired"
    expires = query.lease_expires_at
    if query.status is QueryStatus.LEASED and expires is not None and expires > now:
        return f"query {query.id} is leased to another labeller"
    return f"labeller {labeller_id} holds no lease on query {query.id}"


def _why_refused(session: Session, query: Query, *, labeller_id: int, now: datetime) -> Exception:
    """Why the conditional update in submit_label changed nothing (read only on refusal)."""
    if not get_row(session, Labeller, labeller_id).active:
        return Revoked(f"labeller {labeller_id} is deactivated")
    status = get_row(session, Run, query.run_id).status
    if status not in LABELLABLE:
        return RunClosed(f"run {query.run_id} is {status}: it takes no more answers")
    return LeaseError(_why_no_lease(query, labeller_id=labeller_id, now=now))


def clamp_shown_at(
    shown_at: datetime | None, *, leased_at: datetime | None, now: datetime
) -> datetime | None:
    """`shown_at` within [leased_at, now]: a page cannot show a pair before it was leased, nor
    after it was answered, whatever the browser's clock says. Naive times are taken as UTC."""
    if shown_at is None:
        return None
    try:
        shown = shown_at.replace(tzinfo=UTC) if shown_at.tzinfo is None else shown_at
        shown = shown.astimezone(UTC)
    except OverflowError:
        raise ValueError(f"shown_at {shown_at.isoformat()} is out of range") from None
    if leased_at is not None and shown < leased_at:
        shown = leased_at
    return min(shown, now)


def submit_label(
    session: Session,
    *,
    query_id: int,
    labeller_id: int,
    choice: Choice | str,
    left_is_first: bool,
    shown_at: datetime | None = None,
    source: LabelSource | str = LabelSource.HUMAN,
) -> tuple[Label, bool]:
    """Store the answer of the labeller holding the query's lease; (label, created).

    A repeat of a stored answer returns the stored label with created=False and changes nothing
    (a double click, a retried request). Otherwise the labeller must be active (else Revoked),
    the query's run running or paused (else RunClosed: an answer after a stop is refused, while
    those stored before it stay and are used when the run is requeued), and the labeller must
    hold an unexpired lease on the query (else LeaseError); all three are checked by the one
    conditional update that takes the answer. `shown_at` is stored within [the lease's start,
    now] (`clamp_shown_at`). The lease ends; the query becomes `labelled` once it has
    `needs_labels` answers, else pending again; the run's `labels_used` grows by one whatever the
    answer (cant_tell and skip count against the budget too).
    """
    choice = Choice(choice)
    source = LabelSource(source)
    now = utcnow()
    with transaction(session):
        label = _stored_label(session, query_id=query_id, labeller_id=labeller_id)
        if label is not None:
            detach(session, label)
            return label, False
        query = get_row(session, Query, query_id)
        shown_at = clamp_shown_at(shown_at, leased_at=query.leased_at, now=now)
        active = select(Labeller.id).where(Labeller.id == labeller_id, Labeller.active.is_(True))
        open_run = select(Run.id).where(Run.id == query.run_id, Run.status.in_(LABELLABLE))
        taken = changed(
            session,
            update(Query)
            .where(
                Query.id == query_id,
                Query.status == QueryStatus.LEASED,
                Query.lease_holder == labeller_id,
                Query.lease_expires_at > now,
                active.exists(),
                open_run.exists(),
            )
            .values(
                label_count=Query.label_count + 1,
                status=case(
                    (Query.label_count + 1 >= Query.needs_labels, QueryStatus.LABELLED.value),
                    else_=QueryStatus.PENDING.value,
                ),
                lease_holder=None,
                lease_expires_at=None,
                leased_at=None,
            ),
        )
        if not taken:
            # A concurrent twin of this very submit may have won (PostgreSQL).
            label = _stored_label(session, query_id=query_id, labeller_id=labeller_id)
            if label is not None:
                detach(session, label)
                return label, False
            raise _why_refused(session, query, labeller_id=labeller_id, now=now)
        label = Label(
            query_id=query_id,
            run_id=query.run_id,
            labeller_id=labeller_id,
            choice=choice,
            left_is_first=left_is_first,
            preferred=preferred_segment(choice, left_is_first),
            source=source,
            shown_at=shown_at,
            answered_at=now,
        )
        session.add(label)
        changed(
            session,
            update(Run).where(Run.id == query.run_id).values(labels_used=Run.labels_used + 1),
        )
        detach(session, label)
    return label, True


def consume_labels(session: Session, *, run_id: int) -> list[Label]:
    """Take the run's labels no consumer has taken yet, oldest first, marking them consumed."""
    now = utcnow()
    with transaction(session):
        # Consumers of one run take turns (a row lock on PostgreSQL; SQLite runs one write
        # transaction at a time anyway), so they never wait on each other's label rows.
        run = session.scalars(select(Run.id).where(Run.id == run_id).with_for_update()).first()
        if run is None:
            raise NotFound(f"run {run_id} does not exist")
        ids = session.scalars(
            update(Label)
            .where(Label.run_id == run_id, Label.consumed_at.is_(None))
            .values(consumed_at=now)
            .returning(Label.id),
            execution_options={"synchronize_session": False},
        ).all()
        labels = _labels_where(session, Label.id.in_(ids)) if ids else []
    return labels


def labels_for_queries(session: Session, *, query_ids: Sequence[int]) -> list[Label]:
    """Every stored label of these queries, consumed or not, oldest first."""
    with transaction(session):
        labels = _labels_where(session, Label.query_id.in_(query_ids)) if query_ids else []
    return labels


def _labels_where(session: Session, condition: ColumnElement[bool]) -> list[Label]:
    labels = list(
        session.scalars(
            select(Label)
            .where(condition)
            .order_by(Label.id)
            .execution_options(populate_existing=True)
        )
    )
    detach(session, *labels)
    return labels

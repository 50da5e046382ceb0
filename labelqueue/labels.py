"""Labels: a labeller's answer to a leased query, and the trainer taking the answers.

Taking labels safely: `consume_labels` marks labels consumed in the same transaction that
returns them, so a consumer that dies before the commit loses nothing and two consumers never
get the same label. A trainer that dies after the commit but before its next checkpoint resumes
from that checkpoint, which holds the ids of its open round's queries; `labels_for_queries`
returns their labels whether consumed or not, so nothing taken after the checkpoint is lost.
"""

from __future__ import annotations

import hmac
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import ColumnElement, Integer, String, bindparam, case, insert, select, update
from sqlalchemy.orm import Session

from labelqueue.entry_test import decide
from labelqueue.errors import (
    Invalid,
    LeaseError,
    NotFound,
    OtherRun,
    Revoked,
    RunClosed,
    StaleToken,
)
from labelqueue.gold import pause_if_below
from labelqueue.models import (
    INVITEES,
    INVITES,
    LABELLERS,
    LABELS,
    QUERIES,
    RUNS,
    Label,
    LabelSource,
    QueryStatus,
    Run,
    UTCDateTime,
    utcnow,
)
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.queries import LABELLABLE, one_of
from labelqueue.transaction import (
    detach,
    driver_transaction,
    reading,
    snapshot,
    transaction,
)
from runvocab.answers import (
    FLAG_NOTE_MAX,
    Answer,
    Click,
    Flag,
    answer_of_click,
    click_of_answer,
)

_LABELLER = bindparam("labeller", type_=Integer())
_QUERY = bindparam("query", type_=Integer())
_NOW = bindparam("at", type_=UTCDateTime())
_STORED = select(*LABELS.c).where(
    LABELS.c.query_id == _QUERY, LABELS.c.labeller_id == _LABELLER, LABELS.c.withdrawn_at.is_(None)
)
_STORED_LABEL = Prepared(_STORED)
# The query as the submit needs it, and the id of this labeller's label of it if there is one.
_ASKED = Prepared(select(
    QUERIES.c.run_id,
    QUERIES.c.leased_at,
    QUERIES.c.gold,
    QUERIES.c.practice,
    _STORED.with_only_columns(LABELS.c.id).scalar_subquery().label("stored"),
).where(QUERIES.c.id == _QUERY))
def _asker(*, token: bool) -> list[ColumnElement[bool]]:
    """The answering labeller active, and with `token` its token the one whose hash
    `token_hash` names."""
    labeller = [LABELLERS.c.id == _LABELLER, LABELLERS.c.active.is_(True)]
    if token:
        labeller.append(LABELLERS.c.token_hash == bindparam("token_hash", type_=String()))
    return labeller


def _take_answer(*, token: bool) -> Prepared:
    """The conditional update that takes an answer: the labeller active (and with `token`, its
    token the one whose hash `token_hash` names), holding a live lease on a running run's
    query."""
    labeller = _asker(token=token)
    return Prepared(
        update(QUERIES)
        .where(
            QUERIES.c.id == _QUERY,
            QUERIES.c.status == QueryStatus.LEASED,
            QUERIES.c.lease_holder == _LABELLER,
            QUERIES.c.lease_expires_at > _NOW,
            select(LABELLERS.c.id).where(*labeller).exists(),
            select(RUNS.c.id)
            .where(RUNS.c.id == QUERIES.c.run_id, one_of(RUNS.c.status, LABELLABLE))
            .exists(),
        )
        .values(
            label_count=QUERIES.c.label_count + 1,
            status=case(
                (QUERIES.c.label_count + 1 >= QUERIES.c.needs_labels,
                 QueryStatus.LABELLED.value),
                else_=QueryStatus.PENDING.value,
            ),
            lease_holder=None,
            lease_expires_at=None,
            leased_at=None,
        )
    )


def _take_practice(*, token: bool) -> Prepared:
    """The conditional update that takes a practice answer: the labeller active (and with
    `token`, its token the one `token_hash` names), the practice pair open, its run running or
    paused, and not another run than the labeller's invite is for. A practice pair is shown to
    everyone at once, without a lease (so the lease's check of the invite's run is made here):
    the update changes nothing but orders concurrent answers to the pair (a row lock on
    PostgreSQL)."""
    labeller = _asker(token=token)
    return Prepared(
        update(QUERIES)
        .where(
            QUERIES.c.id == _QUERY,
            QUERIES.c.practice.is_(True),
            one_of(QUERIES.c.status, (QueryStatus.PENDING, QueryStatus.LEASED)),
            select(LABELLERS.c.id).where(*labeller).exists(),
            ~_other_run(),
            select(RUNS.c.id)
            .where(RUNS.c.id == QUERIES.c.run_id, one_of(RUNS.c.status, LABELLABLE))
            .exists(),
        )
        .values(label_count=QUERIES.c.label_count)
    )


def _other_run() -> ColumnElement[bool]:
    """The answering labeller joined by an invite for another run than the query's."""
    return (select(INVITEES.c.labeller_id)
            .join(INVITES, INVITES.c.id == INVITEES.c.invite_id)
            .where(INVITEES.c.labeller_id == _LABELLER, INVITES.c.run_id.is_not(None),
                   INVITES.c.run_id != QUERIES.c.run_id)
            .exists())


_TAKE_ANSWER = _take_answer(token=False)
_TAKE_ANSWER_WITH_TOKEN = _take_answer(token=True)
_TAKE_PRACTICE = _take_practice(token=False)
_TAKE_PRACTICE_WITH_TOKEN = _take_practice(token=True)
_LABEL_COLUMNS = [column for column in LABELS.c if not column.primary_key]
_INSERT_LABEL = Prepared(
    insert(LABELS)
    .values({column.name: bindparam(column.name, type_=column.type) for column in _LABEL_COLUMNS})
    .returning(LABELS.c.id)
)
_COUNT_LABEL = Prepared(
    update(RUNS)
    .where(RUNS.c.id == bindparam("run", type_=Integer()))
    .values(labels_used=RUNS.c.labels_used + 1)
)


_LOCK_RUN = Prepared(
    select(RUNS.c.id).where(RUNS.c.id == bindparam("run", type_=Integer())).with_for_update()
)


def _stored_label(connection: DriverConnection, params: dict[str, Any]) -> Label | None:
    row = _STORED_LABEL.first(connection, params)
    return None if row is None else snapshot(Label, row._asdict())


_REFUSAL = Prepared(
    select(
        LABELLERS.c.active,
        LABELLERS.c.token_hash,
        RUNS.c.status.label("run_status"),
        QUERIES.c.run_id,
        QUERIES.c.status,
        QUERIES.c.lease_holder,
        QUERIES.c.lease_expires_at,
        INVITES.c.run_id.label("invite_run"),
    )
    .select_from(QUERIES)
    .join(RUNS, RUNS.c.id == QUERIES.c.run_id)
    .join(LABELLERS, LABELLERS.c.id == _LABELLER)
    .outerjoin(INVITEES, INVITEES.c.labeller_id == LABELLERS.c.id)
    .outerjoin(INVITES, INVITES.c.id == INVITEES.c.invite_id)
    .where(QUERIES.c.id == _QUERY)
)


def _why_refused(connection: DriverConnection, params: dict[str, Any]) -> Exception:
    """Why the conditional update in submit_label changed nothing (read only on refusal)."""
    labeller_id, query_id, now = params["labeller"], params["query"], params["at"]
    row = _REFUSAL.first(connection, params)
    if row is None:
        return NotFound(f"labeller {labeller_id} does not exist")
    if not row.active:
        return Revoked(f"labeller {labeller_id} is deactivated")
    token = params.get("token_hash")
    if token is not None and not hmac.compare_digest(row.token_hash, token):
        return StaleToken(f"labeller {labeller_id}'s token was replaced by a new one")
    if row.invite_run is not None and row.invite_run != row.run_id:
        return OtherRun(f"you joined this study for run {row.invite_run}: pairs of run "
                        f"{row.run_id} are not yours to label")
    if row.run_status not in LABELLABLE:
        return RunClosed(f"run {row.run_id} is {row.run_status}: it takes no more answers")
    status, expires = QueryStatus(row.status), row.lease_expires_at
    if status in (QueryStatus.LABELLED, QueryStatus.CANCELLED):
        why = f"query {query_id} is {status}: it takes no more answers"
    elif status is QueryStatus.LEASED and row.lease_holder == labeller_id:
        why = f"labeller {labeller_id}'s lease on query {query_id} has expired"
    elif status is QueryStatus.LEASED and expires is not None and expires > now:
        why = f"query {query_id} is leased to another labeller"
    else:
        why = f"labeller {labeller_id} holds no lease on query {query_id}"
    return LeaseError(why)


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
        raise Invalid(f"shown_at {shown_at.isoformat()} is out of range") from None
    if leased_at is not None and shown < leased_at:
        shown = leased_at
    return min(shown, now)


def check_flag(choice: Click, flag: Flag | str | None,
               note: str | None) -> tuple[Flag | None, str | None]:
    """A flag and its note as stored (the note stripped, empty as none); Invalid naming the
    problem for a flag on an answer other than a skip, a note without a flag, an unknown flag
    or a note too long."""
    note = (note or "").strip() or None
    if flag is None:
        if note is not None:
            raise Invalid("flag_note needs a flag")
        return None, None
    try:
        flag = Flag(flag)
    except ValueError:
        raise Invalid(f"unknown flag {flag!r}; valid: "
                         + ", ".join(f.value for f in Flag)) from None
    if choice is not Click.SKIP:
        raise Invalid(f"a flagged pair is skipped, not answered: send choice 'skip' with the "
                         f"flag, not {choice.value!r}")
    if note is not None and len(note) > FLAG_NOTE_MAX:
        raise Invalid(f"flag_note is {len(note)} characters long; at most {FLAG_NOTE_MAX}")
    return flag, note


def submit_label(
    session: Session,
    *,
    query_id: int,
    labeller_id: int,
    choice: Click | str,
    left_is_first: bool,
    shown_at: datetime | None = None,
    source: LabelSource | str = LabelSource.HUMAN,
    flag: Flag | str | None = None,
    flag_note: str | None = None,
    token_hash: str | None = None,
) -> tuple[Label, bool]:
    """Store the answer of the labeller holding the query's lease; (label, created).

    A repeat of a stored answer returns the stored label with created=False and changes nothing
    (a double click, a retried request). Otherwise the labeller must be active (else Revoked),
    the query's run running or paused (else RunClosed: an answer after a stop is refused, while
    those stored before it stay and are used when the run is requeued), and the labeller must
    hold an unexpired lease on the query (else LeaseError); all three are checked by the one
    conditional update that takes the answer, as is, given `token_hash` (the hash of the bearer
    token a person answers with), that the token is still theirs (else StaleToken). `shown_at`
    is stored within [the lease's start, now] (`clamp_shown_at`). The lease ends; the query
    becomes `labelled` once it has `needs_labels` answers, else pending again; the run's
    `labels_used` grows by one whatever the answer (cant_tell and skip count against the budget
    too), unless the query is a gold pair: a gold answer costs no budget, and may pause the
    labeller on the run (`labelqueue.gold`).

    An answer to one of the run's practice pairs (`labelqueue.practice`) needs no lease (the
    pair is shown to every newcomer at once): it is stored with `practice` set, costs no
    budget and checks no gold threshold; the last one may decide the labeller's entry test
    (`labelqueue.entry_test`). A labeller who joined by an invite for another run may answer
    neither (OtherRun): the lease serves them their invite's run only.

    `flag` marks the pair as one nobody can judge (`runvocab.answers.Flag`), with an optional
    `flag_note`; only a skip may carry one (Invalid otherwise), so the flagging answer itself is
    never trained on. The pair may be, when `feedback.labels_per_query` asks several people and
    the others answered it: skips are not answers, and theirs decide
    (`runvocab.answers.aggregate`).
    """
    choice = Click(choice)
    flag, flag_note = check_flag(choice, flag, flag_note)
    return _store(session, query_id=query_id, labeller_id=labeller_id,
                  answer=answer_of_click(choice, left_is_first), choice=choice,
                  left_is_first=left_is_first, shown_at=shown_at, source=LabelSource(source),
                  flag=flag, flag_note=flag_note, token_hash=token_hash)


def submit_answer(
    session: Session,
    *,
    query_id: int,
    labeller_id: int,
    answer: Answer | str,
    source: LabelSource | str = LabelSource.SCRIPTED,
) -> tuple[Label, bool]:
    """Store the answer, in segment terms, of a labeller that sees no screen (the scripted
    teacher) and holds the query's lease; (label, created), on `submit_label`'s terms. The label
    records the first segment on the left, and the click that gives `answer` there."""
    answer = Answer(answer)
    return _store(session, query_id=query_id, labeller_id=labeller_id, answer=answer,
                  choice=click_of_answer(answer, left_is_first=True), left_is_first=True,
                  shown_at=None, source=LabelSource(source), flag=None, flag_note=None,
                  token_hash=None)


def _store(
    session: Session,
    *,
    query_id: int,
    labeller_id: int,
    answer: Answer,
    choice: Click,
    left_is_first: bool,
    shown_at: datetime | None,
    source: LabelSource,
    flag: Flag | None,
    flag_note: str | None,
    token_hash: str | None,
) -> tuple[Label, bool]:
    """`submit_label`'s store, given the answer and what the screen showed."""
    now = utcnow()
    # Bound parameters are named apart from every column (see lease_next_query).
    params: dict[str, Any] = {"query": query_id, "labeller": labeller_id, "at": now}
    with driver_transaction(session) as connection:
        asked = _ASKED.first(connection, params)
        if asked is None:
            raise NotFound(f"query {query_id} does not exist")
        if asked.stored is not None:
            if asked.practice:  # sent again: decides a test an older race left undecided
                decide(connection, labeller_id=labeller_id, run_id=asked.run_id)
            label = _stored_label(connection, params)
            assert label is not None
            return label, False
        practice = bool(asked.practice)
        if practice:
            take = _TAKE_PRACTICE if token_hash is None else _TAKE_PRACTICE_WITH_TOKEN
        else:
            take = _TAKE_ANSWER if token_hash is None else _TAKE_ANSWER_WITH_TOKEN
        took = take.count(connection, params | {"token_hash": token_hash})
        # A concurrent twin of this very submit may have won (PostgreSQL; for a practice pair,
        # seen once the update above has waited for it).
        label = _stored_label(connection, params) if not took or practice else None
        if label is not None:
            return label, False
        if not took:
            raise _why_refused(connection, params | {"token_hash": token_hash})
        values: dict[str, Any] = {
            "query_id": query_id,
            "run_id": asked.run_id,
            "labeller_id": labeller_id,
            "answer": answer,
            "choice": choice,
            "left_is_first": left_is_first,
            "source": source,
            "shown_at": clamp_shown_at(shown_at, leased_at=asked.leased_at, now=now),
            "answered_at": now,
            "consumed_at": None,
            "withdrawn_at": None,
            "flag": flag,
            "flag_note": flag_note,
            "practice": practice,
        }
        # Only real answers spend the budget: a gold answer measures the labeller instead, and
        # a practice answer (to a gold pair kept apart) does neither. The run's row is locked
        # (PostgreSQL) before the label draws its id, so a run's labels commit in the order of
        # their ids and the answers feed's cursor misses none (`externalruns.feed`); a gold
        # answer's pause check then sees the pause of one before it (never a second insert).
        if not asked.gold:
            _COUNT_LABEL.count(connection, {"run": asked.run_id})
        elif not practice and connection.dialect.name == "postgresql":
            _LOCK_RUN.first(connection, {"run": asked.run_id})
        [inserted] = _INSERT_LABEL.rows(connection, values)
        if asked.gold and not practice:
            pause_if_below(connection, labeller_id=labeller_id, run_id=asked.run_id)
        elif practice:  # the last practice answer decides an invite's entry test
            decide(connection, labeller_id=labeller_id, run_id=asked.run_id)
    return snapshot(Label, {"id": inserted.id, **values}), True


def consume_labels(session: Session, *, run_id: int) -> list[Label]:
    """Take the run's labels no consumer has taken yet, oldest first, marking them consumed.

    A label another transaction holds now (an undo taking it back, on PostgreSQL) is left for a
    later call: withdrawn, it is never taken; if the undo is refused, the next call takes it.
    """
    now = utcnow()
    untaken = (Label.run_id == run_id) & Label.consumed_at.is_(None) & Label.withdrawn_at.is_(None)
    with transaction(session):
        # Consumers of one run take turns (a row lock on PostgreSQL; SQLite runs one write
        # transaction at a time anyway), so they never wait on each other's label rows.
        run = session.scalars(select(Run.id).where(Run.id == run_id).with_for_update()).first()
        if run is None:
            raise NotFound(f"run {run_id} does not exist")
        # An undo locks its label, then the query and the run: waiting here for its label while
        # holding the run would deadlock, so a label locked now is skipped, not waited for.
        free = session.scalars(
            select(Label.id).where(untaken).with_for_update(skip_locked=True)
        ).all()
        ids = session.scalars(
            update(Label)
            .where(Label.id.in_(free), untaken)
            .values(consumed_at=now)
            .returning(Label.id),
            execution_options={"synchronize_session": False},
        ).all() if free else []
        labels = _labels_where(session, Label.id.in_(ids)) if ids else []
    return labels


def labels_for_queries(session: Session, *, query_ids: Sequence[int]) -> list[Label]:
    """Every standing label of these queries (not withdrawn), consumed or not, oldest first."""
    standing = Label.query_id.in_(query_ids) & Label.withdrawn_at.is_(None)
    with reading(session):
        labels = _labels_where(session, standing) if query_ids else []
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

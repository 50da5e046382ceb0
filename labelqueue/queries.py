"""Queries: pushed by the worker, leased to one labeller at a time, answered in labels.py.

A query is open when its run is running or paused (a paused run stops training, but its queries
can still be answered), it still needs labels, and it is pending or its lease has run out. An
expired lease needs no sweeper: the next lease simply takes the query over.
"""

from __future__ import annotations

import hmac
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import (
    ColumnElement,
    FromClause,
    Integer,
    Select,
    and_,
    bindparam,
    exists,
    insert,
    or_,
    select,
    update,
)
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.coerce import clip_key, finite
from labelqueue.entry_test import EntryFailed, decide_late, refusal, untested
from labelqueue.errors import Conflict, Invalid, NotFound, OtherRun, Revoked, StaleToken
from labelqueue.gold import (
    GOLD_NEEDS_LABELS,
    SCHEDULE_KEY,
    GoldSettings,
    Paused,
    gold_due,
    gold_pick,
    gold_share,
    pause_notice,
)
from labelqueue.keys import server_key
from labelqueue.models import (
    INVITEES,
    INVITES,
    LABELLERS,
    LABELS,
    PAUSES,
    QUERIES,
    RUNS,
    Label,
    Query,
    QueryStatus,
    Run,
    RunStatus,
    TeacherKind,
    UTCDateTime,
    utcnow,
)
from labelqueue.practice import next_practice, reserve, shows_practice
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.run_config import FEEDBACK, run_feedback
from labelqueue.transaction import (
    changed,
    detach,
    driver_transaction,
    get_row,
    snapshot,
    transaction,
)
from labelqueue.waiting import asked
from runvocab.answers import Answer
from runvocab.query_fields import PROVENANCE, QUERY_FIELD_NAMES, QUERY_FIELDS, FieldType, QueryField

LEASE_SECONDS = 120.0
LABELLABLE = (RunStatus.RUNNING, RunStatus.PAUSED)

# How a pushed value is stored, by declared type (`runvocab.query_fields`). int() and float()
# also turn the trainer's NumPy scalars into values every driver takes.
_STORE: dict[FieldType, Callable[[Any], Any]] = {
    "int": int,
    "float": float,
    "bool": bool,
    "str": str,
    "floats": lambda values: [float(x) for x in values],
    "answer": Answer,
    "clip": clip_key,
}
_REQUIRED = frozenset(field.name for field in QUERY_FIELDS if not field.optional)


def _stored(field: QueryField, value: Any) -> Any:
    if value is None:
        if not field.nullable:
            raise Invalid(f"query field {field.name} may not be null")
        return None
    if field.type == "float" and field.nullable:
        return finite(value)  # "no value" (a uniform pick's NaN score) is stored as null
    return _STORE[field.type](value)


def checked_query_fields(spec: Mapping[str, Any]) -> dict[str, Any]:
    """One query's fields by name, as stored (see `push_queries`); Invalid for an unknown or
    missing field, or too few answers asked."""
    unknown = set(spec) - set(QUERY_FIELD_NAMES)
    missing = _REQUIRED - set(spec)
    if unknown or missing:
        raise Invalid(f"query fields: unknown {sorted(unknown)}, missing {sorted(missing)}")
    fields = {field.name: _stored(field, spec.get(field.name, field.default))
              for field in QUERY_FIELDS}
    if fields["gold"]:
        fields["needs_labels"] = GOLD_NEEDS_LABELS
    if fields["needs_labels"] < 1:
        raise Invalid("needs_labels must be at least 1")
    return fields


def push_queries(
    session: Session, *, run_id: int, queries: Sequence[Mapping[str, Any]]
) -> list[int]:
    """Store a round's queries as pending; their ids, in order.

    Each dict holds the fields `runvocab.query_fields.QUERY_FIELDS` declares, by name: the
    required ones (round, position, segment_length, the trajectory and start of both sides) and
    any optional ones (the trainer always gives the four ground-truth returns); a gold pair
    (`labelqueue.gold`) takes every labeller's answer whatever its needs_labels says.
    Invalid for an unknown or missing field, a null where the field takes none, or a clip
    key outside the clips folder.
    Idempotent per (run, round, position): a run resumed from an older checkpoint that pushes
    the same round again gets the stored ids back; a different pair at a stored position
    raises Conflict.
    """
    specs = [checked_query_fields(spec) for spec in queries]
    rounds = sorted({spec["round"] for spec in specs})
    provenance = [QUERIES.c[name] for name in PROVENANCE]
    now = utcnow()
    # One INSERT for the round, with rows built before the transaction: the worker holds the
    # database's write lock, which every labeller's answer waits for, as briefly as it can.
    with transaction(session):
        if session.execute(select(RUNS.c.id).where(RUNS.c.id == run_id)).first() is None:
            raise NotFound(f"run {run_id} does not exist")
        stored = {
            (row.round, row.position): row
            for row in session.execute(
                select(QUERIES.c.id, QUERIES.c.round, QUERIES.c.position, *provenance).where(
                    QUERIES.c.run_id == run_id, QUERIES.c.round.in_(rounds)
                )
            )
        }
        new = []
        for spec in specs:
            row = stored.get((spec["round"], spec["position"]))
            if row is None:
                fresh = {"run_id": run_id, "status": QueryStatus.PENDING, "created_at": now,
                         "practice": False}
                new.append(spec | fresh)
            elif any(getattr(row, name) != spec[name] for name in PROVENANCE):
                raise Conflict(
                    f"run {run_id} round {spec['round']} position {spec['position']} "
                    f"already holds a different pair (query {row.id})"
                )
        ids = {key: row.id for key, row in stored.items()}
        if new:
            reserve(session, run_id=run_id, specs=new)
            try:
                inserted = session.execute(
                    insert(QUERIES).returning(QUERIES.c.id, sort_by_parameter_order=True), new
                ).scalars().all()
            except IntegrityError as error:
                pushed_twice = f"run {run_id}: the same queries were pushed concurrently"
                raise Conflict(pushed_twice) from error
            keys = [(row["round"], row["position"]) for row in new]
            ids |= dict(zip(keys, inserted, strict=True))
    return [ids[(spec["round"], spec["position"])] for spec in specs]


def set_clips(
    session: Session, *, query_id: int, first_clip: str | None, second_clip: str | None
) -> Query:
    """Attach rendered clips (storage keys relative to the clips folder) to a query."""
    first_clip, second_clip = clip_key(first_clip), clip_key(second_clip)
    with transaction(session):
        query = get_row(session, Query, query_id)
        query.first_clip, query.second_clip = first_clip, second_clip
        detach(session, query)
    return query


def cancel_queries(session: Session, *, run_id: int, query_ids: Sequence[int] | None = None) -> int:
    """Close a run's queries (all, or those named): withdraw the open ones, and mark the answers
    they have taken (consumed), so none can be taken back once its round has closed
    (`labelqueue.undo`); how many queries were withdrawn.

    A labeller holding a lease on one gets LeaseError when it submits.
    """
    condition = [
        Query.run_id == run_id,
        Query.status.in_([QueryStatus.PENDING, QueryStatus.LEASED]),
    ]
    answers = [Label.run_id == run_id, Label.consumed_at.is_(None), Label.withdrawn_at.is_(None)]
    if query_ids is not None:
        condition.append(Query.id.in_(query_ids))
        answers.append(Label.query_id.in_(query_ids))
    with transaction(session):
        get_row(session, Run, run_id)
        # The labels before the queries, in an undo's order (its label, then its query): an undo
        # under way commits first, and its pair, leased again, is then withdrawn here.
        session.execute(update(Label).where(*answers).values(consumed_at=utcnow()),
                        execution_options={"synchronize_session": False})
        return changed(
            session,
            update(Query)
            .where(*condition)
            .values(
                status=QueryStatus.CANCELLED,
                lease_holder=None,
                lease_expires_at=None,
                leased_at=None,
            ),
        )


def one_of(column: ColumnElement[Any], values: Sequence[Any]) -> ColumnElement[bool]:
    """`column IN values` written as ORs of equalities (the same plan on SQLite and PostgreSQL):
    SQLAlchemy renders an IN list anew at every execution, even in a statement built once."""
    return or_(*(column == value for value in values))


def _free(queries: FromClause, now: ColumnElement[datetime]) -> ColumnElement[bool]:
    """Still wanting labels, and pending or with its lease run out."""
    return and_(
        # Spelled out first so the (run_id, status, id) index skips a run's answered queries.
        one_of(queries.c.status, (QueryStatus.PENDING, QueryStatus.LEASED)),
        queries.c.label_count < queries.c.needs_labels,
        or_(
            queries.c.status == QueryStatus.PENDING,
            and_(queries.c.status == QueryStatus.LEASED, queries.c.lease_expires_at <= now),
        ),
    )


# The lease's statements, built once: SQLAlchemy then reuses their compiled SQL and cache keys.
# Parameters are named apart from every column: an UPDATE sets a column a parameter names.
_NOW = bindparam("at", type_=UTCDateTime())
_EXPIRES = bindparam("until", type_=UTCDateTime())
_LABELLER = bindparam("labeller", type_=Integer())
_MINE = and_(QUERIES.c.lease_holder == _LABELLER, QUERIES.c.status == QueryStatus.LEASED)
# The labeller, with each live lease it holds (one row with no lease when it holds none), the
# teacher of the run asked for (none when no run is asked for, or it does not exist), and its
# invite's entry test and run (none: it joined by no invite, or by one for all runs).
_ASKED_TEACHER = (
    select(RUNS.c.teacher).where(RUNS.c.id == bindparam("run")).scalar_subquery().label("teacher")
)
_HOLDER = Prepared(
    select(LABELLERS.c.active, QUERIES.c.id, QUERIES.c.run_id, RUNS.c.status, _ASKED_TEACHER,
           LABELLERS.c.token_hash, INVITEES.c.entry_passed, INVITEES.c.entry_correct,
           INVITES.c.entry_pass, INVITES.c.run_id.label("invite_run"))
    .select_from(LABELLERS)
    .outerjoin(INVITEES, INVITEES.c.labeller_id == LABELLERS.c.id)
    .outerjoin(INVITES, INVITES.c.id == INVITEES.c.invite_id)
    .outerjoin(
        QUERIES,
        and_(
            QUERIES.c.lease_holder == LABELLERS.c.id,
            QUERIES.c.status == QueryStatus.LEASED,
            QUERIES.c.lease_expires_at > _NOW,
        ),
    )
    .outerjoin(RUNS, RUNS.c.id == QUERIES.c.run_id)
    .where(LABELLERS.c.id == _LABELLER)
)
_HELD = bindparam("query", type_=Integer())
_RENEW_STATEMENT = (
    update(QUERIES)
    .where(QUERIES.c.id == _HELD, _MINE, QUERIES.c.lease_expires_at > _NOW)
    .values(lease_expires_at=_EXPIRES)
)
_RENEW = Prepared(_RENEW_STATEMENT)
# A reload is not served on a run that has paused the labeller (an undo leases a pair back).
_RENEW_RETURNING = Prepared(_RENEW_STATEMENT.where(~exists().where(
    PAUSES.c.run_id == QUERIES.c.run_id, PAUSES.c.labeller_id == _LABELLER)).returning(*QUERIES.c))
_RELEASE = Prepared(
    update(QUERIES)
    .where(QUERIES.c.id == _HELD, _MINE)
    .values(status=QueryStatus.PENDING, lease_holder=None, lease_expires_at=None, leased_at=None)
)


def _oldest(*, of_run: bool, gold: bool, only_id: bool = False, after: bool = False,
            lock: bool = True, between: int = 0) -> Select[Any]:
    """The oldest open query (gold pair or not) the labeller has not answered, of one run or of
    any human-taught run, on a run that has not paused the labeller: its id, run and the run's
    config; with `after`, the oldest whose id is above the parameter `after`. Locked with SKIP
    LOCKED on PostgreSQL (unless not `lock`: a look only), so concurrent leases take different
    queries instead of queueing for one."""
    candidate = QUERIES.alias("candidate")
    # A standing answer: one taken back lets the labeller answer again (and the partial
    # unique index on standing labels makes this a lookup, not a scan of every label).
    answered = exists().where(
        LABELS.c.query_id == candidate.c.id,
        LABELS.c.labeller_id == _LABELLER,
        LABELS.c.withdrawn_at.is_(None),
    )
    paused = exists().where(
        PAUSES.c.run_id == candidate.c.run_id, PAUSES.c.labeller_id == _LABELLER
    )
    servable = or_(
        RUNS.c.teacher == TeacherKind.SCRIPTED,
        and_(candidate.c.first_clip.is_not(None), candidate.c.second_clip.is_not(None)),
    )
    which = (
        candidate.c.run_id == bindparam("run") if of_run else RUNS.c.teacher == TeacherKind.HUMAN
    )
    columns = ((candidate.c.id,) if only_id
               else (candidate.c.id, candidate.c.run_id, RUNS.c.config, FEEDBACK))
    oldest = (
        select(*columns)
        .join(RUNS, RUNS.c.id == candidate.c.run_id)
        .where(candidate.c.gold.is_(gold), one_of(RUNS.c.status, LABELLABLE))
        .where(_free(candidate, _NOW), ~answered, ~paused, servable, which)
        .order_by(candidate.c.id)
        .limit(1)
    )
    if gold:  # practice pairs are gold pairs kept apart: never a check pair (practice.py)
        oldest = oldest.where(candidate.c.practice.is_(False))
    if after or between:
        oldest = oldest.where(candidate.c.id > bindparam("after", type_=Integer()))
    if between:  # up to `between` of them, below the parameter `before`
        oldest = oldest.where(candidate.c.id < bindparam("before", type_=Integer()))
        oldest = oldest.limit(between)
    return oldest.with_for_update(of=candidate, skip_locked=True) if lock else oldest


def _lease(which: ColumnElement[Any]) -> Prepared:
    """Lease the query `which` names if it is still free, returning its row."""
    return Prepared(
        update(QUERIES)
        .where(QUERIES.c.id == which, _free(QUERIES, _NOW))
        .values(
            status=QueryStatus.LEASED,
            lease_holder=_LABELLER,
            lease_expires_at=_EXPIRES,
            leased_at=_NOW,
        )
        .returning(*QUERIES.c)
    )


_TAKE_OF_ANY_HUMAN_RUN = _lease(_oldest(of_run=False, gold=False, only_id=True).scalar_subquery())
_TAKE_OF_RUN = _lease(_oldest(of_run=True, gold=False, only_id=True).scalar_subquery())
_GOLD_OF_ANY_HUMAN_RUN = Prepared(_oldest(of_run=False, gold=True, lock=False))
_GOLD_OF_RUN = Prepared(_oldest(of_run=True, gold=True, lock=False))
NO_ID = 2**31 - 1
"""above every query id (the column is a 32-bit integer)"""
GOLD_CHOICES = 64
"""gold pairs a check is drawn among at most (the oldest of those that may come next)"""
_GOLD_BETWEEN = Prepared(
    _oldest(of_run=True, gold=True, only_id=True, lock=False, between=GOLD_CHOICES))
_FIRST_OF_ANY_HUMAN_RUN = Prepared(_oldest(of_run=False, gold=False, only_id=True, lock=False))
_FIRST_OF_RUN = Prepared(_oldest(of_run=True, gold=False, only_id=True, lock=False))
_TAKE_PAIR = _lease(bindparam("pair", type_=Integer()))
# Why nothing was leased, when the labeller is paused on the runs asked about.
_PAUSE_STATEMENT = (
    select(PAUSES.c.gold_answers, PAUSES.c.gold_correct, RUNS.c.config, FEEDBACK)
    .join(RUNS, RUNS.c.id == PAUSES.c.run_id)
    .where(PAUSES.c.labeller_id == _LABELLER, one_of(RUNS.c.status, LABELLABLE))
)
_PAUSE = Prepared(_PAUSE_STATEMENT)
_PAUSE_ON_RUN = Prepared(_PAUSE_STATEMENT.where(PAUSES.c.run_id == bindparam("run")))


def lease_next_query(
    session: Session,
    *,
    labeller_id: int,
    run_id: int | None = None,
    lease_seconds: float = LEASE_SECONDS,
    ahead_of: int | None = None,
    gold: bool = True,
    for_people: bool = False,
    token_hash: str | None = None,
) -> Query | None:
    """Lease the oldest open query this labeller has no standing answer to (one it took back
    counts as unanswered); None when there is none.

    Without `run_id` only human-taught runs are served; a human-taught run's queries are served
    once both clips exist (a scripted teacher needs none). A query is leased to one labeller at
    a time. A labeller holds at most one lease: asking again while it holds one returns the same
    query with the lease renewed (a page reload); asking for another run releases it.

    `ahead_of`: the query the labeller is looking at. Its lease is kept (and renewed) and a
    second query is leased besides it, so a page can preload the next pair; asking again with
    the same `ahead_of` returns the same second query.

    A newcomer on a run with practice pairs is shown them first (`labelqueue.practice`). One
    whose invite has an entry test gets no other pair until it is decided
    (`labelqueue.entry_test.untested`): with no practice pair to show yet, nothing.

    Gold pairs (`labelqueue.gold`) are mixed in at their run's rate unless `gold` is false (the
    run's own scripted teacher). A labeller paused on a run gets none of its queries, nor keeps
    a lease there but the one it is shown; when that leaves nothing to lease, Paused says why.

    A labeller who joined by an invite for one run is served that run only: asking without
    `run_id` asks for it, and asking for another is refused (OtherRun), so they neither spend
    another run's budget nor wait on a run that is not theirs.

    `for_people`: a person asks, so the run asked for must exist (else NotFound) and be taught
    by people (else Conflict). `token_hash`: the hash of the bearer token the person asked with
    (`labellers.hash_token`), which must still be theirs (else StaleToken), read in this
    transaction: a new token stops the old one at once, whichever process made it.
    """
    now = utcnow()
    params: dict[str, Any] = {
        "labeller": labeller_id,
        "at": now,
        "until": now + timedelta(seconds=lease_seconds),
        "run": run_id,
    }
    key = server_key(session, SCHEDULE_KEY) if gold else None  # read once per process
    with driver_transaction(session) as connection:
        holder = _HOLDER.rows(connection, params)
        _check_asker(holder, params, for_people=for_people, token_hash=token_hash)
        # A newcomer's practice pairs come first, shown without a lease of their own; one whose
        # entry test is still to decide gets nothing else until it is.
        practice = (next_practice(connection, params, shown=ahead_of, until=params["until"])
                    if gold else None)
        waits = practice is None and untested(connection, holder[0], labeller_id)
        # One an older race left undecided, every practice answer in, is decided now (and one
        # who failed refused once that is committed).
        late = decide_late(connection, labeller_id=labeller_id) if waits else None
        if late is not None:
            waits = not late[0]
        row, kept = (None, False) if practice is not None or waits else _renew_or_release(
            connection, holder, params, ahead_of=ahead_of)
        paused = None
        if practice is None and row is None and not waits:
            try:
                row = _take_next(connection, params, key=key, ahead_of=ahead_of)
            except Paused as error:  # raised once the leases given back above are committed
                paused = error
        if for_people and paused is None:  # how long a participant waits with nothing to
            # label: a pair on their screen (`ahead_of`, a lease of theirs or a practice pair)
            # is something to label; a paused one waits for no pair
            got = practice is not None or row is not None or kept or (
                ahead_of is not None and shows_practice(connection, ahead_of))
            asked(connection, params, got=got)
    if late is not None and not late[0]:  # once the decision is committed
        raise EntryFailed(refusal(late[1], holder[0].entry_pass))
    if paused is not None:
        raise paused
    if practice is not None:
        return snapshot(Query, practice)
    return None if row is None else snapshot(Query, row._asdict())


def _check_asker(holder: Sequence[Any], params: dict[str, Any], *, for_people: bool,
                 token_hash: str | None) -> None:
    """Refuse a lease to a labeller that is missing or deactivated, that asks with a replaced
    token, that failed its invite's entry test (`labelqueue.entry_test`), that joined by an
    invite for another run than the one asked for, or (a person) for a run that is missing or
    taught by a script. A one-run invitee asking for no run is asked for their invite's run
    (`params` changed)."""
    labeller_id, run_id = params["labeller"], params["run"]
    if not holder:
        raise NotFound(f"labeller {labeller_id} does not exist")
    if not holder[0].active:
        raise Revoked(f"labeller {labeller_id} is deactivated")
    if token_hash is not None and not hmac.compare_digest(holder[0].token_hash, token_hash):
        raise StaleToken(f"labeller {labeller_id}'s token was replaced by a new one")
    if holder[0].entry_passed is not None and not holder[0].entry_passed:
        raise EntryFailed(refusal(holder[0].entry_correct, holder[0].entry_pass))
    own = holder[0].invite_run
    if own is not None and run_id not in (None, own):
        raise OtherRun.asking(own, run_id)
    if own is not None:
        params["run"] = own
    if for_people and run_id is not None:
        if holder[0].teacher is None:
            raise NotFound(f"run {run_id} does not exist")
        if holder[0].teacher != TeacherKind.HUMAN:
            raise Conflict(f"run {run_id} is taught by a scripted teacher, not by people")


def _renew_or_release(connection: DriverConnection, holder: Sequence[Any],
                      params: dict[str, Any], *, ahead_of: int | None) -> tuple[Any | None, bool]:
    """The labeller's live leases (at most the one it is shown and the one ahead of it): the
    one shown (`ahead_of`) is renewed; one of the run asked for is a reload, renewed and
    returned; the rest, held for another run, a run that closed or one that paused the
    labeller, are freed for others.
    (the reload's row or None, whether the one shown was renewed)"""
    others, kept = [], False
    for _, held, held_run, status, *_ in holder:
        if held is None:
            continue
        if held == ahead_of:
            kept = _RENEW.count(connection, params | {"query": held}) > 0
            continue
        if status in LABELLABLE and params["run"] in (None, held_run):
            row = _RENEW_RETURNING.first(connection, params | {"query": held})
            if row is not None:
                return row, kept
        others.append(held)
    for other in others:
        _RELEASE.count(connection, params | {"query": other})
    return None, kept


def _take_next(connection: DriverConnection, params: dict[str, Any], *, key: bytes | None,
               ahead_of: int | None) -> Any | None:
    """Lease the pair `_choose` picks (`key`: the gold schedule's, None for no gold), else the
    oldest open query; None when there is none, or Paused when a pause is why."""
    chosen = _choose(connection, params, key, ahead_of) if key is not None else None
    row = None if chosen is None else _TAKE_PAIR.first(connection, params | {"pair": chosen})
    if row is None:  # no gold on these runs, or the pair was taken meanwhile (PostgreSQL)
        take = _TAKE_OF_ANY_HUMAN_RUN if params["run"] is None else _TAKE_OF_RUN
        row = take.first(connection, params)
    if row is None:
        pause = (_PAUSE if params["run"] is None else _PAUSE_ON_RUN).first(connection, params)
        if pause is not None:
            raise Paused(pause_notice(pause.gold_answers, pause.gold_correct,
                                      GoldSettings.of(run_feedback(pause))))
    return row


def _choose(connection: DriverConnection, params: dict[str, Any], key: bytes,
            ahead_of: int | None) -> int | None:
    """The labeller's next pair where the runs asked about have gold pairs: a gold pair when
    their share of gold answers is due (`labelqueue.gold`), else the oldest open query; None
    where they have no gold pair (the plain lease then).

    A gold pair comes in the order the other queries come in: never one behind the furthest
    query they answered on the run or the one they are shown (`ahead_of`), never one after the
    next ordinary query. A labeller's first check is drawn among those that may come, at
    random under `key` (so newcomers do not all get the run's oldest); later ones are the
    oldest that may come, as a check passed over could never come later. A gold lease and an
    ordinary one make the same statements, in the same order: neither the ids a labeller is
    served, nor their order, nor the time a lease takes tell a gold pair from the others."""
    oldest = (_GOLD_OF_ANY_HUMAN_RUN if params["run"] is None else _GOLD_OF_RUN).first(
        connection, params)
    if oldest is None:
        return None
    labeller, run_id = params["labeller"], oldest.run_id
    share = gold_share(connection, labeller_id=labeller, run_id=run_id)
    first = (_FIRST_OF_ANY_HUMAN_RUN if params["run"] is None else _FIRST_OF_RUN).first(
        connection, params)
    golds = _GOLD_BETWEEN.rows(connection, params | {
        "run": run_id, "after": max(share.furthest, ahead_of or 0),
        "before": NO_ID if first is None else first.id})
    due = gold_due(share, key=key, labeller_id=labeller, run_id=run_id,
                   rate=GoldSettings.of(run_feedback(oldest)).rate)
    if due and golds:
        # A newcomer's first check is drawn among them while ordinary pairs are left to hide
        # it among; later checks are the oldest that may come, so none is skipped for good.
        among = len(golds) if share.gold == 0 and first is not None else 1
        return int(golds[gold_pick(key, labeller_id=labeller, run_id=run_id,
                                   answers=share.answers, among=among)].id)
    return None if first is None else int(first.id)

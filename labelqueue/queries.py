"""Queries: pushed by the worker, leased to one labeller at a time, answered in labels.py.

A query is open when its run is running or paused (a paused run stops training, but its queries
can still be answered), it still needs labels, and it is pending or its lease has run out. An
expired lease needs no sweeper: the next lease simply takes the query over.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from datetime import datetime, timedelta
from typing import Any

from sqlalchemy import ColumnElement, and_, exists, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from labelqueue.coerce import clip_key, finite
from labelqueue.errors import Conflict, Revoked
from labelqueue.models import (
    Label,
    Labeller,
    Query,
    QueryStatus,
    Run,
    RunStatus,
    ShadowChoice,
    TeacherKind,
    utcnow,
)
from labelqueue.transaction import changed, detach, get_row, transaction

LEASE_SECONDS = 120.0
LABELLABLE = (RunStatus.RUNNING, RunStatus.PAUSED)

_INTS = (
    "round",
    "position",
    "segment_length",
    "first_trajectory",
    "first_start",
    "second_trajectory",
    "second_start",
)
_FLOATS = (
    "first_segment_return",
    "second_segment_return",
    "first_trajectory_return",
    "second_trajectory_return",
)
_OPTIONAL = (
    "step",
    "first_skill",
    "second_skill",
    "first_clip",
    "second_clip",
    "model_p",
    "score",
    "rule",
    "needs_labels",
    "shadow_choice",
    "distinguishable",
)
# What makes a stored query the same pair as a pushed one.
_PROVENANCE = (
    "segment_length",
    "first_trajectory",
    "first_start",
    "second_trajectory",
    "second_start",
)


def _query_fields(spec: Mapping[str, Any]) -> dict[str, Any]:
    unknown = set(spec) - set(_INTS) - set(_FLOATS) - set(_OPTIONAL)
    missing = (set(_INTS) | set(_FLOATS)) - set(spec)
    if unknown or missing:
        raise ValueError(f"query fields: unknown {sorted(unknown)}, missing {sorted(missing)}")
    # int()/float() also turn the trainer's NumPy scalars into values every driver takes.
    fields: dict[str, Any] = {name: int(spec[name]) for name in _INTS}
    fields |= {name: float(spec[name]) for name in _FLOATS}
    for side in ("first", "second"):
        skill = spec.get(f"{side}_skill")
        fields[f"{side}_skill"] = None if skill is None else [float(x) for x in skill]
        fields[f"{side}_clip"] = clip_key(spec.get(f"{side}_clip"))
    fields["step"] = None if spec.get("step") is None else int(spec["step"])
    fields["model_p"] = finite(spec.get("model_p"))
    fields["score"] = finite(spec.get("score"))
    fields["rule"] = spec.get("rule")
    shadow = spec.get("shadow_choice")
    fields["shadow_choice"] = None if shadow is None else ShadowChoice(shadow)
    distinguishable = spec.get("distinguishable")
    fields["distinguishable"] = None if distinguishable is None else bool(distinguishable)
    fields["needs_labels"] = int(spec.get("needs_labels", 1))
    if fields["needs_labels"] < 1:
        raise ValueError("needs_labels must be at least 1")
    return fields


def push_queries(
    session: Session, *, run_id: int, queries: Sequence[Mapping[str, Any]]
) -> list[int]:
    """Store a round's queries as pending; their ids, in order.

    Each dict holds `Query` columns by name: round, position, segment_length, the trajectory
    and start of both sides, the four ground-truth returns (`first_segment_return`, ...,
    `second_trajectory_return`), and optionally step, first/second_skill, first/second_clip,
    model_p, score, rule, needs_labels, and the hidden shadow_choice (the run's scripted
    teacher's answer: first, second, equal, cant_tell or skip) and distinguishable.
    Idempotent per (run, round, position): a run resumed from an older checkpoint that pushes
    the same round again gets the stored ids back; a different pair at a stored position
    raises Conflict.
    """
    specs = [_query_fields(spec) for spec in queries]
    with transaction(session):
        get_row(session, Run, run_id)
        rounds = sorted({spec["round"] for spec in specs})
        stored = {
            (query.round, query.position): query
            for query in session.scalars(
                select(Query).where(Query.run_id == run_id, Query.round.in_(rounds))
            )
        }
        rows: list[Query] = []
        for spec in specs:
            query = stored.get((spec["round"], spec["position"]))
            if query is None:
                query = Query(run_id=run_id, status=QueryStatus.PENDING, **spec)
                session.add(query)
            elif any(getattr(query, name) != spec[name] for name in _PROVENANCE):
                raise Conflict(
                    f"run {run_id} round {spec['round']} position {spec['position']} "
                    f"already holds a different pair (query {query.id})"
                )
            rows.append(query)
        try:
            session.flush()
        except IntegrityError as error:
            raise Conflict(f"run {run_id}: the same queries were pushed concurrently") from error
        ids = [query.id for query in rows]
    return ids


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
    """Withdraw a run's open queries (all, or those named); how many were withdrawn.

    A labeller holding a lease on one gets LeaseError when it submits.
    """
    condition = [
        Query.run_id == run_id,
        Query.status.in_([QueryStatus.PENDING, QueryStatus.LEASED]),
    ]
    if query_ids is not None:
        condition.append(Query.id.in_(query_ids))
    with transaction(session):
        get_row(session, Run, run_id)
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


def _free(now: datetime) -> ColumnElement[bool]:
    """Still wanting labels, and pending or with its lease run out."""
    return and_(
        # Spelled out first so the (run_id, status, id) index skips a run's answered queries.
        Query.status.in_((QueryStatus.PENDING, QueryStatus.LEASED)),
        Query.label_count < Query.needs_labels,
        or_(
            Query.status == QueryStatus.PENDING,
            and_(Query.status == QueryStatus.LEASED, Query.lease_expires_at <= now),
        ),
    )


def lease_next_query(
    session: Session,
    *,
    labeller_id: int,
    run_id: int | None = None,
    lease_seconds: float = LEASE_SECONDS,
    ahead_of: int | None = None,
) -> Query | None:
    """Lease the oldest open query this labeller has not answered; None when there is none.

    Without `run_id` only human-taught runs are served; a human-taught run's queries are served
    once both clips exist (a scripted teacher needs none). A query is leased to one labeller at
    a time. A labeller holds at most one lease: asking again while it holds one returns the same
    query with the lease renewed (a page reload); asking for another run releases it.

    `ahead_of`: the query the labeller is looking at. Its lease is kept (and renewed) and a
    second query is leased besides it, so a page can preload the next pair; asking again with
    the same `ahead_of` returns the same second query.
    """
    now = utcnow()
    expires = now + timedelta(seconds=lease_seconds)
    mine = and_(Query.lease_holder == labeller_id, Query.status == QueryStatus.LEASED)
    with transaction(session):
        if not get_row(session, Labeller, labeller_id).active:
            raise Revoked(f"labeller {labeller_id} is deactivated")
        if ahead_of is not None:
            changed(
                session,
                update(Query)
                .where(Query.id == ahead_of, mine, Query.lease_expires_at > now)
                .values(lease_expires_at=expires),
            )
            mine = and_(mine, Query.id != ahead_of)

        held_query = (
            select(Query.id)
            .join(Run, Run.id == Query.run_id)
            .where(mine, Query.lease_expires_at > now, Run.status.in_(LABELLABLE))
        )
        if run_id is not None:
            held_query = held_query.where(Query.run_id == run_id)
        held = session.scalars(held_query).first()
        if held is not None and changed(
            session, update(Query).where(Query.id == held, mine).values(lease_expires_at=expires)
        ):
            query = get_row(session, Query, held)
            detach(session, query)
            return query
        changed(
            session,
            update(Query)
            .where(mine, Query.lease_expires_at > now)
            .values(
                status=QueryStatus.PENDING,
                lease_holder=None,
                lease_expires_at=None,
                leased_at=None,
            ),
        )

        answered = exists().where(Label.query_id == Query.id, Label.labeller_id == labeller_id)
        servable = or_(
            Run.teacher == TeacherKind.SCRIPTED,
            and_(Query.first_clip.is_not(None), Query.second_clip.is_not(None)),
        )
        candidates = (
            select(Query.id)
            .join(Run, Run.id == Query.run_id)
            .where(Run.status.in_(LABELLABLE), _free(now), ~answered, servable)
            .where(Run.teacher == TeacherKind.HUMAN if run_id is None else Query.run_id == run_id)
            .order_by(Query.id)
            .limit(20)
        )
        while ids := session.scalars(candidates).all():
            for query_id in ids:
                # Loses only to a concurrent lease of the same query (PostgreSQL); try the next.
                if changed(
                    session,
                    update(Query)
                    .where(Query.id == query_id, _free(now))
                    .values(
                        status=QueryStatus.LEASED,
                        lease_holder=labeller_id,
                        lease_expires_at=expires,
                        leased_at=now,
                    ),
                ):
                    query = get_row(session, Query, query_id)
                    detach(session, query)
                    return query
    return None

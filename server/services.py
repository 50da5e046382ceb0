"""What the routes do, as keyword-only functions over a session: reads and small compositions
of queue operations. Reads run in `reading` blocks: read-only transactions that end with the
block and, on SQLite, take no lock (WAL runs them beside the writer).
"""

from __future__ import annotations

import time
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from externalruns.pairs import known_answer
from labelqueue import (
    Invalid,
    Invitee,
    Label,
    Labeller,
    LabelSource,
    NotFound,
    Query,
    Run,
    create_run,
    lease_next_query,
    submit_label,
    withdraw_label,
)
from labelqueue import reading as reading  # the routes' own reads (stats, curves) use it too
from labelqueue.practice import explain, practice_step
from labelqueue.runs import EXTERNAL
from runvocab.answers import Answer
from server import clips
from server.label_schemas import LabelOut, LabelSubmit, NextQuery, PracticeFeedback, PracticeOut
from server.schemas import RunCreate
from server.settings import Settings


def get_run(session: Session, *, run_id: int) -> Run:
    with reading(session):
        run = session.get(Run, run_id, populate_existing=True)
    if run is None:
        raise NotFound(f"run {run_id} does not exist")
    return run


def list_runs(session: Session, *, before: int | None = None,
              limit: int | None = None) -> list[Run]:
    """The runs older than run `before` (every run without it), oldest first; with `limit`,
    the `limit` newest of them."""
    statement = select(Run).where(*([Run.id < before] if before is not None else []))
    with reading(session):
        newest = list(session.scalars(statement.order_by(Run.id.desc()).limit(limit)))
    return newest[::-1]


def list_labellers(session: Session) -> list[Labeller]:
    with reading(session):
        return list(session.scalars(select(Labeller).order_by(Labeller.id)))


def get_query(session: Session, *, query_id: int) -> Query:
    with reading(session):
        query = session.get(Query, query_id, populate_existing=True)
    if query is None:
        raise NotFound(f"query {query_id} does not exist")
    return query


def new_run(session: Session, *, spec: RunCreate) -> Run:
    assert spec.budget is not None, "the route fills in the preset's budget"
    return create_run(
        session,
        name=spec.name or f"{spec.task}-{spec.algo}-s{spec.seed}",
        task=spec.task,
        algo=spec.algo,
        budget=spec.budget,
        preset=spec.preset,
        seed=spec.seed,
        teacher=spec.teacher,
        teacher_params=spec.teacher_params,
        config=spec.config,
        instruction=spec.instruction,
        clip_size=spec.clip_size,
    )


def next_query(
    session: Session,
    *,
    settings: Settings,
    labeller_id: int,
    run_id: int | None,
    ahead_of: int | None = None,
    token_hash: str | None = None,
) -> NextQuery | None:
    """Lease the labeller's next query and describe it without ground truth; None if none. A
    run asked for must exist and be taught by people (checked in the lease's transaction)."""
    query = lease_next_query(
        session,
        labeller_id=labeller_id,
        run_id=run_id,
        lease_seconds=settings.lease_seconds,
        ahead_of=ahead_of,
        for_people=True,
        token_hash=token_hash,
    )
    if query is None:
        return None
    return shown_query(settings=settings, query=query, labeller_id=labeller_id, session=session)


def shown_query(*, settings: Settings, query: Query, labeller_id: int,
                session: Session | None = None) -> NextQuery:
    """A query leased to the labeller as its page shows it: signed clip URLs in the labeller's
    side order, and nothing that hints the answer; with `session`, which practice pair a
    practice pair is (said so: its answer is explained once given)."""
    assert query.lease_expires_at is not None
    first_left = clips.left_is_first(settings=settings, query_id=query.id, labeller_id=labeller_id)
    now = time.time()
    urls = {
        side: clips.signed_clip_url(settings=settings, query_id=query.id, side=side, now=now)
        for side in clips.SIDES
    }
    starts: tuple[int | None, int | None] = (
        (query.first_start, query.second_start) if first_left
        else (query.second_start, query.first_start))
    if query.rule == EXTERNAL:  # its client's uploads: of no step of an episode we know
        starts = (None, None)
    return NextQuery(
        query_id=query.id,
        run_id=query.run_id,
        lease_expires_at=query.lease_expires_at,
        left_clip_url=urls["first" if first_left else "second"],
        right_clip_url=urls["second" if first_left else "first"],
        left_is_first=first_left,
        segment_length=query.segment_length,
        left_start_step=starts[0],
        right_start_step=starts[1],
        practice=practice_of(session, query=query) if query.practice else None,
    )


def practice_of(session: Session | None, *, query: Query) -> PracticeOut | None:
    """Which of the run's practice pairs this one is (a gold or ordinary pair takes no trip
    here: nothing about it tells it apart)."""
    if session is None:
        return None
    step = practice_step(session, run_id=query.run_id, query_id=query.id)
    return PracticeOut(index=step.index, of=step.of)


def answer_out(
    session: Session, *, settings: Settings, labeller_id: int, query_id: int, body: LabelSubmit,
    token_hash: str | None = None,
) -> tuple[LabelOut, bool]:
    """`submit_answer`, as the page gets it: a practice answer comes explained (which clip the
    true reward prefers, by a ratio: never the returns)."""
    label, created = submit_answer(session, settings=settings, labeller_id=labeller_id,
                                   query_id=query_id, body=body, token_hash=token_hash)
    out = LabelOut.model_validate(label)
    if label.practice:  # an answer of the practice round
        query = get_query(session, query_id=query_id)
        first, second = query.first_segment_return, query.second_segment_return
        if first is None or second is None:  # an external gold pair known by its answer only
            first_better = known_answer(session, query_id=query_id) == Answer.FIRST
            better = "left" if first_better == label.left_is_first else "right"
            text = f"The {better} clip is better."
        else:
            left, right = (first, second) if label.left_is_first else (second, first)
            better, text = explain(left_return=left, right_return=right)
        step = practice_step(session, run_id=query.run_id, query_id=query.id)
        choice = str(getattr(label.choice, "value", label.choice))
        with reading(session):
            passed = session.scalar(select(Invitee.entry_passed).where(
                Invitee.labeller_id == labeller_id))
        out.practice_feedback = PracticeFeedback(
            index=step.index, of=step.of, better=better,  # type: ignore[arg-type]
            correct=choice == better if choice in ("left", "right", "equal") else None,
            explanation=text,
            entry_test=None if passed is None else "passed" if passed else "failed")
    return out, created


def submit_answer(
    session: Session, *, settings: Settings, labeller_id: int, query_id: int, body: LabelSubmit,
    token_hash: str | None = None,
) -> tuple[Label, bool]:
    """Store a person's answer; (label, created). The side order is the server's own; a page
    that sends the `left_is_first` next-query gave as a check, and sends another, is refused
    (Invalid, 422), since it showed the pair otherwise than the server records."""
    first_left = clips.left_is_first(settings=settings, query_id=query_id, labeller_id=labeller_id)
    if body.left_is_first is not None and body.left_is_first != first_left:
        get_query(session, query_id=query_id)  # an unknown query is a 404 first
        raise Invalid(
            f"left_is_first={str(body.left_is_first).lower()} is not the side order this server "
            f"showed for query {query_id} ({str(first_left).lower()}); reload the page"
        )
    return submit_label(
        session,
        query_id=query_id,
        labeller_id=labeller_id,
        choice=body.choice,
        left_is_first=first_left,
        shown_at=body.shown_at,
        source=LabelSource.HUMAN,
        flag=body.flag,
        flag_note=body.flag_note,
        token_hash=token_hash,
    )


def take_back_answer(
    session: Session, *, settings: Settings, labeller_id: int, query_id: int, keep: int | None,
    token_hash: str | None = None,
) -> tuple[Label, NextQuery]:
    """Withdraw the labeller's answer to the query (`labelqueue.undo`); the label as withdrawn
    and the query, leased to the labeller again, as its page shows it."""
    withdrawn = withdraw_label(session, query_id=query_id, labeller_id=labeller_id, keep=keep,
                               lease_seconds=settings.lease_seconds, token_hash=token_hash)
    return withdrawn.label, shown_query(settings=settings, query=withdrawn.query,
                                        labeller_id=labeller_id, session=session)


def clip_path(session: Session, *, settings: Settings, query_id: int, side: str) -> Path:
    """The file of a query's clip; NotFound when the query, side or file is not there."""
    query = get_query(session, query_id=query_id)
    path = clips.clip_file(settings=settings, query=query, side=side)
    if path is None:
        raise NotFound(f"query {query_id} has no {side!r} clip (not rendered yet, or no such side)")
    return path

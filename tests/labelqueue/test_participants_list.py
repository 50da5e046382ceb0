"""The participants list of a study (SQLite and PostgreSQL): each participant's answers, state
and code as a study with people in every state shows them, kept completions included; made
with as many statements for six participants as for nine. Their codes checked at once, with as
many statements for two codes as for a dozen."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from queue_helpers import query_spec
from sqlalchemy import Engine, event, select, update
from sqlalchemy.orm import Session

from crowdstudy.invites import create_invite, join_invite
from crowdstudy.participants import participants, verify_codes
from labelqueue import (
    Invite,
    Invitee,
    LabellerPause,
    Run,
    claim_run,
    create_run,
    lease_next_query,
    push_queries,
    set_labeller_active,
    submit_label,
)
from labelqueue.models import utcnow

COLUMNS = ("participant", "decisive", "equal", "cant_tell", "skips", "practice", "paused",
           "counted", "complete", "why", "code_valid", "entry_test", "entry_correct", "active")


def human_run(session: Session, worker: str, **config: object) -> int:
    run = create_run(session, name=worker, task="dmc:cheetah_run", algo="pebble", budget=100,
                     teacher="human", config={f"feedback.{k}": v for k, v in config.items()})
    claimed = claim_run(session, worker_id=worker)
    assert claimed is not None and claimed.id == run.id
    return run.id


def answer(session: Session, labeller_id: int, run_id: int, choice: str) -> bool:
    """Lease the labeller's next pair on the run and answer it; whether it was practice."""
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
    assert query is not None
    submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=choice,
                 left_is_first=True)
    return bool(query.practice)


def table(session: Session, invite_id: int) -> list[tuple[Any, ...]]:
    return [tuple(getattr(row, column) for column in COLUMNS)
            for row in participants(session, invite_id=invite_id)]


def kept(session: Session) -> dict[str, str | None]:
    """Each participant's completion as kept (`invitees.completed_why`)."""
    rows = session.execute(select(Invitee.participant, Invitee.completed_why)).all()
    session.commit()
    return {participant: why for participant, why in rows if why is not None}


@contextmanager
def statements(engine: Engine) -> Iterator[list[str]]:
    seen: list[str] = []

    def count(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        seen.append(statement)

    event.listen(engine, "before_cursor_execute", count)
    try:
        yield seen
    finally:
        event.remove(engine, "before_cursor_execute", count)


@dataclass(frozen=True)
class Study:
    """Two invites whose participants are in every state (`mixed_study`)."""

    one: Invite
    """on a run with a practice pair as its entry test: ann to fay"""
    every: Invite
    """on all runs: gus, hal and ivy"""
    practised: int
    """the first invite's run"""
    people: dict[str, int]
    """each participant's labeller id"""


def mixed_study(session: Session) -> Study:
    """ann reaches the target, bob fails the entry test, cat does nothing, check pairs pause
    dan, eve is deactivated and fay waited with nothing to label; on all runs, gus answers
    short of the target, hal is paused on both runs and ivy does nothing."""
    practised = human_run(session, "w1", practice_pairs=1)
    plain = human_run(session, "w2")
    push_queries(session, run_id=practised, queries=[query_spec(
        0, gold=True, first_segment_return=10.0, second_segment_return=2.0)])
    push_queries(session, run_id=practised, queries=[query_spec(i) for i in range(1, 9)])
    push_queries(session, run_id=plain, queries=[query_spec(i) for i in range(6)])
    week = utcnow() + timedelta(days=7)
    one = create_invite(session, expires_at=week, run_id=practised, entry_pass=1,
                        target_answers=2, completion_code="PAY")
    every = create_invite(session, expires_at=week, target_answers=3)
    people = {name: join_invite(session, code=one.code, participant=name).labeller.id
              for name in ("ann", "bob", "cat", "dan", "eve", "fay")}
    people |= {name: join_invite(session, code=every.code, participant=name).labeller.id
               for name in ("gus", "hal", "ivy")}

    def on_practised(name: str, *choices: str) -> None:
        for choice in choices:
            answer(session, people[name], practised, choice)

    on_practised("ann", "left", "left", "right")  # passes, then reaches the target
    on_practised("bob", "right")  # fails the entry test
    on_practised("dan", "left", "skip")  # passes; check pairs pause him below
    on_practised("eve", "left", "equal")  # passes; deactivated below
    on_practised("fay", "left", "cant_tell")  # passes; waited with nothing to label below
    for choice in ("left", "right", "cant_tell"):
        answer(session, people["gus"], plain, choice)
    for run_id, name in ((practised, "dan"), (practised, "hal"), (plain, "hal")):
        session.add(LabellerPause(run_id=run_id, labeller_id=people[name], gold_answers=4,
                                  gold_correct=1))
    session.commit()
    set_labeller_active(session, labeller_id=people["eve"], active=False)
    with session.begin():
        session.execute(update(Invitee).where(Invitee.labeller_id == people["fay"])
                        .values(nothing_left_at=utcnow()))
    return Study(one, every, practised, people)


def test_the_list_shows_each_participants_state_and_costs_no_statement_per_participant(
    session: Session, engine: Engine
) -> None:
    study = mixed_study(session)
    one, every, practised = study.one, study.every, study.practised
    assert table(session, one.id) == [
        ("ann", 2, 0, 0, 0, 1, False, 2, True, "target", True, "passed", 1, True),
        ("bob", 0, 0, 0, 0, 1, False, 0, True, "entry_failed", False, "failed", 0, True),
        ("cat", 0, 0, 0, 0, 0, False, 0, False, None, False, "undecided", None, True),
        ("dan", 0, 0, 0, 1, 1, True, 0, True, "paused", True, "passed", 1, True),
        ("eve", 0, 1, 0, 0, 1, False, 1, False, None, False, "passed", 1, False),
        ("fay", 0, 0, 1, 0, 1, False, 0, True, "nothing_left", True, "passed", 1, True),
    ]
    assert table(session, every.id) == [
        ("gus", 2, 0, 1, 0, 0, False, 2, False, None, False, None, None, True),
        ("hal", 0, 0, 0, 0, 0, True, 0, True, "paused", True, None, None, True),
        ("ivy", 0, 0, 0, 0, 0, False, 0, False, None, False, None, None, True),
    ]
    assert kept(session) == {"ann": "target", "dan": "paused", "fay": "nothing_left",
                             "hal": "paused"}
    with statements(engine) as six:
        participants(session, invite_id=one.id)

    # Both runs over: who had no end yet ends with them; the ends found before are kept.
    with session.begin():
        session.execute(update(Run).values(labels_used=100))
    assert [(row[0], row[9]) for row in table(session, every.id)] == [
        ("gus", "runs_over"), ("hal", "paused"), ("ivy", "runs_over")]
    assert [(row[0], row[9], row[10]) for row in table(session, one.id)] == [
        ("ann", "target", True), ("bob", "entry_failed", False), ("cat", "runs_over", True),
        ("dan", "paused", True), ("eve", "runs_over", False), ("fay", "nothing_left", True)]

    with session.begin():  # the runs open again
        session.execute(update(Run).values(labels_used=0))
    for name in ("jo", "kim", "lee"):  # three more, with answers: no more statements
        labeller = join_invite(session, code=one.code, participant=name).labeller.id
        answer(session, labeller, practised, "left")
    participants(session, invite_id=one.id)
    with statements(engine) as nine:
        assert len(participants(session, invite_id=one.id)) == 9
    assert len(nine) == len(six)


def test_many_codes_are_checked_in_every_state_with_no_statement_per_code(
    session: Session, engine: Engine
) -> None:
    study = mixed_study(session)
    code = {row.participant: row.completion_code for invite in (study.one, study.every)
            for row in participants(session, invite_id=invite.id)}  # completions kept
    names = ("ann", "bob", "cat", "dan", "eve", "fay", "gus", "hal", "ivy")
    # Typed as people type them: lower case, without the study code, with blank lines.
    given = [code[name] for name in names] + [
        "", code["ann"].lower(), code["dan"].removeprefix("PAY-"), "PAY-0000-0000-0000"]

    def checked(invite_id: int | None = None) -> list[tuple[Any, ...]]:
        return [(c.code, c.participant, c.labeller_id, c.invite_id, c.valid, c.why)
                for c in verify_codes(session, given, invite_id=invite_id)]

    def row(name: str, valid: bool, why: str, typed: str | None = None) -> tuple[Any, ...]:
        invite = study.one if name in names[:6] else study.every
        return (typed or code[name], name, study.people[name], invite.id, valid, why)

    unknown = ("PAY-0000-0000-0000", None, None, None, False, "unknown")
    assert checked() == [
        row("ann", True, "target"), row("bob", False, "entry_failed"),
        row("cat", False, "not_complete"), row("dan", True, "paused"),
        row("eve", False, "not_complete"), row("fay", True, "nothing_left"),
        row("gus", False, "not_complete"), row("hal", True, "paused"),
        row("ivy", False, "not_complete"),
        # Retyped, ann's and dan's codes are still theirs, and given again: paid once.
        row("ann", False, "target", code["ann"].lower()),
        row("dan", False, "paused", code["dan"].removeprefix("PAY-")), unknown]
    assert [c.repeat for c in verify_codes(session, given)] == [False] * 9 + [True, True, False]
    other = [row(name, False, "other_study") for name in ("gus", "hal", "ivy")]
    assert checked(study.one.id)[6:9] == other
    assert checked(study.one.id)[:6] == checked()[:6]

    # Two codes, one of each invite, read as many statements as the whole list.
    with statements(engine) as two:
        verify_codes(session, [code["ann"], code["gus"]])
    with statements(engine) as all_of_them:
        assert len(verify_codes(session, given)) == len(given) - 1
    assert len(all_of_them) == len(two)

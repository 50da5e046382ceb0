"""An invite's entry test: a participant must get `entry_pass` of the run's practice pairs
right (`labelqueue.practice`) to go on; one who answers them all with fewer right is let go.

- The test is decided with the answer to the last practice pair (every one of the run's
  `feedback.practice_pairs` answered, standing answers only): passed or failed, stored on the
  participant (`invitees.entry_passed`, `entry_correct`), and it stays decided. One an older
  PostgreSQL left undecided with every answer in (two last answers at once, each counting only
  its own) is decided at their next lease, or their answer sent again (`decide_late`).
- A practice answer is right when it is the better clip by the true reward ("equal" when the
  segments' returns are equal; an external pair's known answer otherwise), as the practice
  explanation says; a can't-tell or a skip is never right.
- Until the test is decided the participant is served practice pairs only (`untested`): with
  none to show (not rendered yet, or the last one on their screen) they get nothing and wait as
  anyone with nothing to label, so nobody starts on real pairs untested. One who already has a
  standing real answer on the run (an older database's) goes on.
- A practice answer of an invite with an entry test is never taken back (`labelqueue.undo`):
  each is explained once given, and the test measures the first try.
- A participant who failed gets no more pairs (`EntryFailed`, a 403, from every lease), holds
  no lease (theirs are let go when the test is decided), has no completion code (their study
  ends as "entry_failed": `crowdstudy.completion.labeller_progress`) and never spends the budget
  (practice answers never do).

For an invite on one run, 1 <= entry_pass <= the run's practice pairs is checked when the invite
is made; an all-runs invite's test is decided on the first run whose practice pairs the
participant has all answered (a run with fewer practice pairs than `entry_pass` fails all),
and until then they are served no real pair of any run (a run without practice pairs gives them
none).
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import Integer, bindparam, func, or_, select, update
from sqlalchemy.orm import Session

from labelqueue.errors import Invalid, QueueError
from labelqueue.models import (
    EXTERNAL_PAIRS,
    INVITEES,
    INVITES,
    LABELS,
    QUERIES,
    RUNS,
    QueryStatus,
)
from labelqueue.practice import practice_pairs
from labelqueue.prepared import DriverConnection, Prepared
from labelqueue.run_config import FEEDBACK, run_feedback
from runvocab.answers import Answer


class EntryFailed(QueueError):
    """The participant failed their invite's entry test: no more pairs, and no code."""


class EntryPassInvalid(Invalid):
    """An invite's `entry_pass` does not fit its run's practice pairs (or is below 1)."""


def refusal(correct: int | None, needed: int | None) -> str:
    """Why a participant who failed the entry test is served nothing (a 403's detail)."""
    return (f"entry test not passed: {correct or 0} of your practice answers were right, and "
            f"this study asks for {needed}; your part in it is over (no completion code)")


def check_entry_pass(session: Session, *, run_id: int | None, entry_pass: int | None) -> None:
    """EntryPassInvalid unless `entry_pass` is none, or at least 1 and (for an invite on one
    run) at most the run's `feedback.practice_pairs`. Called inside the invite's transaction."""
    if entry_pass is None:
        return
    if entry_pass < 1:
        raise EntryPassInvalid(f"entry_pass must be at least 1 (or left out: no entry test), "
                               f"got {entry_pass}")
    if run_id is None:
        return
    row = session.execute(select(RUNS.c.config, FEEDBACK).where(RUNS.c.id == run_id)).one()
    pairs = practice_pairs(run_feedback(row))
    if pairs < 1:
        raise EntryPassInvalid(f"entry_pass needs practice pairs, and run {run_id} has none "
                               "(feedback.practice_pairs = 0): leave entry_pass out, or set "
                               "practice pairs on a new run")
    if entry_pass > pairs:
        raise EntryPassInvalid(f"entry_pass must be from 1 to run {run_id}'s {pairs} practice "
                               f"pairs (feedback.practice_pairs), got {entry_pass}")


def right_answer(first_return: float | None, second_return: float | None,
                 known: Answer | str | None) -> Answer:
    """A practice pair's right answer, in segment terms (`labelqueue.practice.explain`'s)."""
    if known is not None:
        return Answer(known)
    assert first_return is not None and second_return is not None, "a gold pair without truth"
    if first_return == second_return:
        return Answer.EQUAL
    return Answer.FIRST if first_return > second_return else Answer.SECOND


_LABELLER = bindparam("labeller", type_=Integer())
_RUN = bindparam("run", type_=Integer())
_UNDECIDED = Prepared(
    select(INVITES.c.entry_pass, RUNS.c.config, FEEDBACK)
    .select_from(INVITEES)
    .join(INVITES, INVITES.c.id == INVITEES.c.invite_id)
    .join(RUNS, RUNS.c.id == _RUN)
    .where(INVITEES.c.labeller_id == _LABELLER, INVITES.c.entry_pass.is_not(None),
           INVITEES.c.entry_passed.is_(None),
           or_(INVITES.c.run_id.is_(None), INVITES.c.run_id == _RUN))
    # One participant's practice answers take turns here (a row lock on PostgreSQL): the later
    # one counts the earlier's, so two sent at once still decide the test.
    .with_for_update(of=INVITEES)
)
_PRACTISED = Prepared(
    select(LABELS.c.answer, QUERIES.c.first_segment_return, QUERIES.c.second_segment_return,
           EXTERNAL_PAIRS.c.gold_answer)
    .select_from(LABELS)
    .join(QUERIES, QUERIES.c.id == LABELS.c.query_id)
    .outerjoin(EXTERNAL_PAIRS, EXTERNAL_PAIRS.c.query_id == QUERIES.c.id)
    .where(LABELS.c.labeller_id == _LABELLER, LABELS.c.run_id == _RUN,
           LABELS.c.practice.is_(True), LABELS.c.withdrawn_at.is_(None))
)
_PRACTISED_RUNS = Prepared(
    select(LABELS.c.run_id)
    .where(LABELS.c.labeller_id == _LABELLER, LABELS.c.practice.is_(True),
           LABELS.c.withdrawn_at.is_(None))
    .group_by(LABELS.c.run_id).order_by(func.min(LABELS.c.id))
)
_DECIDE = Prepared(
    update(INVITEES)
    .where(INVITEES.c.labeller_id == _LABELLER, INVITEES.c.entry_passed.is_(None))
    .values(entry_passed=bindparam("passed", type_=INVITEES.c.entry_passed.type),
            entry_correct=bindparam("correct", type_=Integer()))
)
_REAL = select(LABELS.c.id).where(LABELS.c.labeller_id == _LABELLER,
                                   LABELS.c.practice.is_(False), LABELS.c.withdrawn_at.is_(None))
_REAL_ON_RUN = Prepared(_REAL.where(LABELS.c.run_id == _RUN).limit(1))
_REAL_ANYWHERE = Prepared(_REAL.limit(1))
_LET_GO = Prepared(
    update(QUERIES)
    .where(QUERIES.c.lease_holder == _LABELLER, QUERIES.c.status == QueryStatus.LEASED)
    .values(status=QueryStatus.PENDING, lease_holder=None, lease_expires_at=None, leased_at=None)
)


def untested(connection: DriverConnection, holder: Any, labeller_id: int) -> bool:
    """Whether the labeller must be served no real pair yet: their invite has an entry test,
    undecided, and they have no standing answer but practice ones on the invite's run (on any
    run, for an all-runs invite). `holder`: the lease's row of the labeller, with its invite's
    `entry_pass`, `entry_passed` and `invite_run`. One who answered real pairs before the test
    was asked of them (an older database) goes on."""
    if holder.entry_pass is None or holder.entry_passed is not None:
        return False
    if holder.invite_run is not None:
        real = _REAL_ON_RUN.first(connection, {"labeller": labeller_id,
                                               "run": holder.invite_run})
    else:
        real = _REAL_ANYWHERE.first(connection, {"labeller": labeller_id})
    return real is None


def decide(connection: DriverConnection, *, labeller_id: int, run_id: int) -> bool | None:
    """After a practice answer, in its transaction: decide the labeller's entry test once they
    have answered all of the run's practice pairs; whether they passed (None: no test, not yet,
    or decided before). One who failed is let go of every lease they hold.

    The participant's row is locked before their answers are counted, so their answers sent at
    once are counted in turn. Locks: the answer's query row, then the participant's, then the
    leases let go; a lease takes the queries' rows and then the participant's, and an
    undecided participant holds no lease of a real pair to let go (`untested`)."""
    decided = _decided(connection, {"labeller": labeller_id, "run": run_id})
    return None if decided is None else decided[0]


def decide_late(connection: DriverConnection, *, labeller_id: int) -> tuple[bool, int] | None:
    """At a request of an undecided participant with no practice pair left to show: decide the
    test on the first run whose practice pairs they have all answered, which an older
    PostgreSQL's race left undecided; (whether they passed, their right answers), or None.
    The participant's row is locked before any query's: they hold no lease (`untested`), and
    the lease then takes its query with SKIP LOCKED."""
    for row in _PRACTISED_RUNS.rows(connection, {"labeller": labeller_id}):
        decided = _decided(connection, {"labeller": labeller_id, "run": row.run_id})
        if decided is not None:
            return decided
    return None


def _decided(connection: DriverConnection, params: dict[str, Any]) -> tuple[bool, int] | None:
    test = _UNDECIDED.first(connection, params)
    if test is None:
        return None
    answers = _PRACTISED.rows(connection, params)
    if len(answers) < practice_pairs(run_feedback(test)):
        return None
    correct = sum(Answer(row.answer) == right_answer(
        row.first_segment_return, row.second_segment_return, row.gold_answer) for row in answers)
    passed = bool(correct >= test.entry_pass)
    _DECIDE.count(connection, params | {"passed": passed, "correct": correct})
    if not passed:
        _LET_GO.count(connection, params)
    return passed, correct

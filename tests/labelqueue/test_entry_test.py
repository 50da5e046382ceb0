"""An invite's entry test in the queue (SQLite and PostgreSQL): decided by the last practice
answer; who fails gets no lease (EntryFailed), holds none, has no code and cannot take a
practice answer back; who passes goes on; entry_pass must fit the run's practice pairs."""

from __future__ import annotations

import contextlib
import threading
from datetime import timedelta

import pytest
from queue_helpers import query_spec
from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from crowdstudy.completion import labeller_progress
from crowdstudy.invites import create_invite, join_invite
from labelqueue import (
    EntryFailed,
    Invalid,
    Invite,
    Invitee,
    Query,
    QueryStatus,
    Run,
    UndoRefused,
    claim_run,
    create_run,
    labels,
    lease_next_query,
    push_queries,
    set_clips,
    submit_label,
    withdraw_label,
)
from labelqueue.entry_test import decide
from labelqueue.models import utcnow


def run_with(session: Session, **config: object) -> int:
    run = create_run(session, name="p", task="dmc:cheetah_run", algo="pebble", budget=100,
                     teacher="human", config={f"feedback.{k}": v for k, v in config.items()})
    claimed = claim_run(session, worker_id="w")
    assert claimed is not None and claimed.id == run.id
    return run.id


def gold(i: int) -> dict[str, object]:
    return query_spec(100 + i, gold=True, first_segment_return=10.0, second_segment_return=2.0)


def labels_used(session: Session, run_id: int) -> int:
    used = session.scalar(select(Run.labels_used).where(Run.id == run_id))
    session.commit()
    return int(used or 0)


def test_the_last_practice_answer_decides_and_who_fails_is_let_go(session: Session) -> None:
    run_id = run_with(session, practice_pairs=2)
    push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(3)])
    push_queries(session, run_id=run_id, queries=[gold(i) for i in range(2)])
    expires = utcnow() + timedelta(days=1)
    with pytest.raises(Invalid, match="entry_pass must be from 1 to run"):
        create_invite(session, expires_at=expires, run_id=run_id, entry_pass=3)
    invite = create_invite(session, expires_at=expires, run_id=run_id, entry_pass=2)
    ann = join_invite(session, code=invite.code, participant="ann").labeller
    bob = join_invite(session, code=invite.code, participant="bob").labeller

    def practise(labeller_id: int, click: str) -> int:
        query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
        assert query is not None and query.practice
        submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=click,
                     left_is_first=True)
        return query.id

    practise(ann.id, "left")  # the first segment is better: right
    practise(ann.id, "left")
    real = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
    assert real is not None and not real.practice  # she passed and goes on

    practise(bob.id, "left")
    held = lease_next_query(session, labeller_id=bob.id, run_id=run_id, ahead_of=None)
    assert held is not None and held.practice
    last = practise(bob.id, "cant_tell")  # not right: 1 of 2
    with pytest.raises(EntryFailed, match="1 of your practice answers were right"):
        lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    with pytest.raises(UndoRefused, match="entry test"):
        withdraw_label(session, query_id=last, labeller_id=bob.id)
    leased = session.scalars(select(Query.id).where(Query.lease_holder == bob.id,
                                                    Query.status == QueryStatus.LEASED)).all()
    session.commit()
    assert leased == []
    progress = labeller_progress(session, labeller_id=bob.id)
    assert (progress.complete, progress.why, progress.completion_code) == (
        True, "entry_failed", None)
    assert not progress.earned and progress.entry_correct == 1
    assert labels_used(session, run_id) == 0  # practice never spends the budget


def test_no_real_pair_is_served_before_the_entry_test_is_decided(session: Session) -> None:
    run_id = run_with(session, practice_pairs=2)
    push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(3)])
    [one, two] = push_queries(session, run_id=run_id, queries=[
        gold(i) | {"first_clip": None, "second_clip": None} for i in range(2)])
    invite = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run_id,
                           entry_pass=2)
    ann = join_invite(session, code=invite.code, participant="ann").labeller

    # The practice pairs are not rendered yet: she waits, rather than start untested.
    assert lease_next_query(session, labeller_id=ann.id, run_id=run_id) is None
    for query_id in (one, two):
        set_clips(session, query_id=query_id, first_clip=f"p{query_id}-a.mp4",
                  second_clip=f"p{query_id}-b.mp4")
    first = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
    assert first is not None and first.practice
    submit_label(session, query_id=first.id, labeller_id=ann.id, choice="left",
                 left_is_first=True)
    last = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
    assert last is not None and last.practice
    # The page preloads behind the last practice pair: nothing, until it is answered.
    assert lease_next_query(session, labeller_id=ann.id, run_id=run_id, ahead_of=last.id) \
        is None
    submit_label(session, query_id=last.id, labeller_id=ann.id, choice="left",
                 left_is_first=True)
    real = lease_next_query(session, labeller_id=ann.id, run_id=run_id, ahead_of=last.id)
    assert real is not None and not real.practice
    assert labeller_progress(session, labeller_id=ann.id).entry_correct == 2


def test_who_answered_real_pairs_before_the_test_was_asked_goes_on(session: Session) -> None:
    run_id = run_with(session, practice_pairs=1)
    push_queries(session, run_id=run_id, queries=[query_spec(i) for i in range(3)])
    invite = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run_id)
    bob = join_invite(session, code=invite.code, participant="bob").labeller
    real = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert real is not None and not real.practice
    submit_label(session, query_id=real.id, labeller_id=bob.id, choice="left",
                 left_is_first=True)
    with session.begin():  # as an older database may hold it: a test he never took
        session.execute(update(Invite).values(entry_pass=1))
    push_queries(session, run_id=run_id, queries=[gold(0)])
    more = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
    assert more is not None and not more.practice


def test_two_last_practice_answers_sent_at_once_decide_the_test(
    url: str, sessions: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each answer, stored and not yet committed, counts the practice answers: on PostgreSQL
    each would see only its own unless the second waits for the first."""
    if not url.startswith("postgresql"):
        pytest.skip("SQLite's writers take turns: one answer commits before the other counts")
    with sessions() as session:
        run_id = run_with(session, practice_pairs=2)
        push_queries(session, run_id=run_id, queries=[gold(i) for i in range(2)]
                     + [query_spec(i) for i in range(2)])
        invite = create_invite(session, expires_at=utcnow() + timedelta(days=1),
                               run_id=run_id, entry_pass=2)
        bob = join_invite(session, code=invite.code, participant="bob").labeller
        first = lease_next_query(session, labeller_id=bob.id, run_id=run_id)
        assert first is not None
        second = lease_next_query(session, labeller_id=bob.id, run_id=run_id, ahead_of=first.id)
        assert second is not None and {first.practice, second.practice} == {True}
    stored, counted = threading.Barrier(2, timeout=10), threading.Barrier(2)

    def decide_when_both_are_stored(*args: object, **kwargs: object) -> object:
        stored.wait()  # both answers stored, neither committed
        decided = decide(*args, **kwargs)
        # Neither commits before both have counted, unless one waits for the other to commit
        # (the lock): then the first gives up waiting here after 2 s.
        with contextlib.suppress(threading.BrokenBarrierError):
            counted.wait(timeout=2)
        return decided

    monkeypatch.setattr(labels, "decide", decide_when_both_are_stored)

    def answer(query_id: int) -> None:
        with sessions() as session:
            submit_label(session, query_id=query_id, labeller_id=bob.id, choice="skip",
                         left_is_first=True)

    threads = [threading.Thread(target=answer, args=(q,)) for q in (first.id, second.id)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    progress = labeller_progress(sessions(), labeller_id=bob.id)
    assert (progress.why, progress.entry_correct) == ("entry_failed", 0)


def left_undecided(session: Session, labeller_id: int) -> None:
    """As an older PostgreSQL race left a participant: every practice answer in, no decision
    (two last answers at once, each counting only its own)."""
    with session.begin():
        session.execute(update(Invitee).where(Invitee.labeller_id == labeller_id)
                        .values(entry_passed=None, entry_correct=None))


def entry_decision(session: Session, labeller_id: int) -> tuple[bool | None, int | None]:
    row = session.execute(select(Invitee.entry_passed, Invitee.entry_correct)
                          .where(Invitee.labeller_id == labeller_id)).one()
    session.commit()
    return row.entry_passed, row.entry_correct


@pytest.mark.parametrize("invite_run", ["one", "all"])
def test_one_left_undecided_with_every_practice_answer_in_is_decided_at_the_next_lease(
        session: Session, invite_run: str) -> None:
    run_id = run_with(session, practice_pairs=2)
    push_queries(session, run_id=run_id, queries=[gold(i) for i in range(2)]
                 + [query_spec(i) for i in range(2)])
    invite = create_invite(session, expires_at=utcnow() + timedelta(days=1),
                           run_id=run_id if invite_run == "one" else None, entry_pass=2)
    asked = run_id if invite_run == "one" else None
    for name, click in (("ann", "left"), ("bob", "right")):  # right, and wrong, twice
        who = join_invite(session, code=invite.code, participant=name).labeller
        for _ in range(2):
            query = lease_next_query(session, labeller_id=who.id, run_id=run_id)
            assert query is not None and query.practice
            submit_label(session, query_id=query.id, labeller_id=who.id, choice=click,
                         left_is_first=True)
        left_undecided(session, who.id)
        if name == "ann":  # she passed, and labels real pairs from her next lease on
            real = lease_next_query(session, labeller_id=who.id, run_id=asked)
            assert real is not None and not real.practice
            assert entry_decision(session, who.id) == (True, 2)
        else:  # he failed, and is told so; the decision stays
            with pytest.raises(EntryFailed, match="0 of your practice answers were right"):
                lease_next_query(session, labeller_id=who.id, run_id=asked)
            assert entry_decision(session, who.id) == (False, 0)
            assert labeller_progress(session, labeller_id=who.id).why == "entry_failed"


def test_one_left_undecided_is_decided_when_their_last_practice_answer_is_sent_again(
        session: Session) -> None:
    run_id = run_with(session, practice_pairs=1)
    push_queries(session, run_id=run_id, queries=[gold(0), query_spec(0)])
    invite = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run_id,
                           entry_pass=1)
    ann = join_invite(session, code=invite.code, participant="ann").labeller
    query = lease_next_query(session, labeller_id=ann.id, run_id=run_id)
    assert query is not None and query.practice
    submit_label(session, query_id=query.id, labeller_id=ann.id, choice="left",
                 left_is_first=True)
    left_undecided(session, ann.id)
    # The page retries the answer whose request the race left without a decision.
    _, created = submit_label(session, query_id=query.id, labeller_id=ann.id, choice="left",
                              left_is_first=True)
    assert not created and entry_decision(session, ann.id) == (True, 1)


def test_a_practice_answer_of_an_entry_test_is_never_taken_back(session: Session) -> None:
    run_id = run_with(session, practice_pairs=2)
    push_queries(session, run_id=run_id, queries=[gold(i) for i in range(2)]
                 + [query_spec(i) for i in range(2)])
    tested = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run_id,
                           entry_pass=2)
    free = create_invite(session, expires_at=utcnow() + timedelta(days=1), run_id=run_id)
    for invite, refused in ((tested, True), (free, False)):
        who = join_invite(session, code=invite.code).labeller
        first = lease_next_query(session, labeller_id=who.id, run_id=run_id)
        assert first is not None and first.practice
        submit_label(session, query_id=first.id, labeller_id=who.id, choice="right",
                     left_is_first=True)  # wrong: the explanation now says so
        if refused:  # the test is undecided yet, and still measures the first try
            with pytest.raises(UndoRefused, match="entry test"):
                withdraw_label(session, query_id=first.id, labeller_id=who.id)
        else:  # plain practice may be tried again
            assert withdraw_label(session, query_id=first.id, labeller_id=who.id).query.practice

"""The answers feed of an external run (`externalruns.feed.answers_after`), on SQLite and on
PostgreSQL: a cursor resumes exactly, an answer taken back comes as a withdrawal, and answers
committed by many labellers at once are each given once, none lost, with no time held back."""

from __future__ import annotations

import contextlib
import threading
from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from externalruns.feed import Cursor, answers_after
from externalruns.pairs import PairSpec, push_pairs
from externalruns.runs import create_external_run
from labelqueue import Label, create_labeller, lease_next_query, submit_label, withdraw_label
from labelqueue.errors import Conflict
from runvocab.clip_format import ClipInfo

CLIPS = {name: ClipInfo("mp4", "h264", 32, 32, 6, 0.2) for name in ("a", "b")}


def external_run(session: Session, *, pairs: int, k: int = 1, gold: int = 0) -> int:
    run = create_external_run(session, name="ext", task="gym:Hopper-v5", budget=pairs * k,
                              labels_per_query=k, gold_rate=0.5 if gold else 0.0)
    push_pairs(session, run_id=run.id, clips=CLIPS, pairs=[
        PairSpec(f"p{i}", "a", "b", returns=(float(i), 0.0)) for i in range(pairs)] + [
        PairSpec(f"g{i}", "a", "b", gold="first") for i in range(gold)])
    return run.id


def answer_one(session: Session, *, run_id: int, labeller_id: int, choice: str = "left") -> int:
    """The labeller answers the next pair of the run; the query's id (0: nothing left)."""
    query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
    if query is None:
        return 0
    submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=choice,
                 left_is_first=True)
    return query.id


def test_the_cursor_resumes_and_a_withdrawal_follows_the_answer_it_takes_back(
    session: Session,
) -> None:
    run_id = external_run(session, pairs=3, k=2)
    ann, _ = create_labeller(session, name="ann")
    bob, _ = create_labeller(session, name="bob")
    start = answers_after(session, run_id=run_id, cursor=Cursor())
    assert (start.events, str(start.cursor), start.open_pairs) == ([], f"{run_id}.0.0", 3)
    first = answer_one(session, run_id=run_id, labeller_id=ann.id)
    answer_one(session, run_id=run_id, labeller_id=bob.id, choice="right")
    read = answers_after(session, run_id=run_id, cursor=start.cursor)
    assert [(e["kind"], e["labeller"], e["answer"]) for e in read.events] == [
        ("answer", "ann", "first"), ("answer", "bob", "second")]
    assert answers_after(session, run_id=run_id, cursor=start.cursor).events == read.events
    withdraw_label(session, query_id=first, labeller_id=ann.id)
    after = answers_after(session, run_id=run_id, cursor=read.cursor)
    [event] = after.events
    assert (event["kind"], event["key"], event["labeller"]) == ("withdrawal", "p0", "ann")
    assert answers_after(session, run_id=run_id, cursor=after.cursor).events == []
    # An answer given and taken back between two reads is never given, nor its withdrawal.
    second = answer_one(session, run_id=run_id, labeller_id=ann.id)
    withdraw_label(session, query_id=second, labeller_id=ann.id)
    assert answers_after(session, run_id=run_id, cursor=after.cursor).events == []


def test_answers_committed_at_once_by_many_labellers_are_each_given_once(
    sessions: sessionmaker[Session],
) -> None:
    """Eight labellers answer 240 pairs (gold ones among them) as fast as they can, taking
    every fifth answer back, while a reader follows the feed with no time held back: every
    answer and withdrawal comes exactly once, and the answers standing at the end are those
    the reader has left when it applies what it read."""
    with sessions() as session:
        run_id = external_run(session, pairs=200, gold=40)
        labellers = [create_labeller(session, name=f"l{i}")[0].id for i in range(8)]
    done = threading.Event()
    events: list[tuple[str, int]] = []

    def follow() -> None:
        cursor = Cursor()
        with sessions() as session:
            while True:
                finished = done.is_set()
                feed = answers_after(session, run_id=run_id, cursor=cursor)
                events.extend((e["kind"], e["label_id"]) for e in feed.events)
                cursor = feed.cursor
                if finished and not feed.events:
                    return

    def answer_all(labeller_id: int) -> int:
        count = 0
        with sessions() as session:
            while query_id := answer_one(session, run_id=run_id, labeller_id=labeller_id):
                count += 1
                if count % 5 == 0:  # taken back at once: answered again at the next lease
                    with contextlib.suppress(Conflict):  # a gold pair another labeller holds
                        withdraw_label(session, query_id=query_id, labeller_id=labeller_id)
        return count

    reader = threading.Thread(target=follow, daemon=True)
    reader.start()
    try:
        with ThreadPoolExecutor(max_workers=8) as pool:
            answered = sum(pool.map(answer_all, labellers, timeout=300))
    finally:
        done.set()
    reader.join(60)
    assert not reader.is_alive() and answered >= 240
    assert len(events) == len(set(events))  # nothing twice
    standing: set[int] = set()
    for kind, label_id in events:
        if kind == "answer":
            standing.add(label_id)
        else:
            assert label_id in standing, f"a withdrawal of label {label_id} before its answer"
            standing.remove(label_id)
    with sessions() as session:
        stored = session.scalars(select(Label.id).where(
            Label.run_id == run_id, Label.withdrawn_at.is_(None))).all()
    assert standing == set(stored)  # nothing lost

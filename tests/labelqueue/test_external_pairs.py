"""Pushes of an external run's pairs at once (`externalruns.pairs.push_pairs`), on SQLite and
on PostgreSQL: they take turns on the run's row, so a key is stored once, each query gets a
place of its own and the budget holds."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import pytest
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

import externalruns.pairs
from externalruns.pairs import PairSpec, Pushed, push_pairs
from externalruns.runs import create_external_run
from labelqueue import Query
from labelqueue.errors import Conflict
from runvocab.clip_format import ClipInfo

CLIPS = {name: ClipInfo("mp4", "h264", 32, 32, 6, 0.2) for name in ("a", "b")}


def test_pushes_at_once_store_each_key_once_within_the_budget(
    sessions: sessionmaker[Session], monkeypatch: pytest.MonkeyPatch
) -> None:
    with sessions() as session:
        run_id = create_external_run(session, name="ext", task="gym:Hopper-v5", budget=4).id
    checked = externalruns.pairs._check_budget

    def slowly(session: Session, **kwargs: Any) -> None:
        checked(session, **kwargs)
        time.sleep(0.3)  # between reading the run's queries and adding to them

    monkeypatch.setattr(externalruns.pairs, "_check_budget", slowly)

    def push(keys: list[str]) -> list[Pushed] | Conflict:
        with sessions() as session:
            try:
                return push_pairs(session, run_id=run_id, clips=CLIPS,
                                  pairs=[PairSpec(key, "a", "b") for key in keys])
            except Conflict as refused:
                return refused

    # A retry racing its first try, and two new pushes of which the budget takes one.
    batches = [["a1", "a2"], ["a1", "a2"], ["b1", "b2"], ["c1", "c2"]]
    with ThreadPoolExecutor(max_workers=4) as pool:
        first, retry, *others = pool.map(push, batches)
    assert isinstance(first, list) and isinstance(retry, list)
    assert [p.query_id for p in first] == [p.query_id for p in retry]
    assert sorted(p.created for p in first + retry) == [False, False, True, True]
    refused = [result for result in others if isinstance(result, Conflict)]
    assert len(refused) == 1 and "budget is 4 answers" in str(refused[0])
    with sessions() as session:
        positions = session.scalars(select(Query.position).where(Query.run_id == run_id)).all()
    assert sorted(positions) == [0, 1, 2, 3]


def test_a_push_the_database_refuses_for_a_stored_key_is_a_conflict(
    session: Session, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Should a push still meet another's row (a unique key or place), it is a Conflict (409)
    that says to push again, not a server error."""
    run_id = create_external_run(session, name="ext", task="gym:Hopper-v5", budget=4).id

    def clash(*_args: Any, **_kwargs: Any) -> None:
        raise IntegrityError("INSERT INTO external_pairs", {}, Exception("duplicate key"))

    monkeypatch.setattr(externalruns.pairs, "_store", clash)
    with pytest.raises(Conflict, match="push again"):
        push_pairs(session, run_id=run_id, clips=CLIPS, pairs=[PairSpec("k", "a", "b")])

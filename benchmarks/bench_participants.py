"""A study's participants list (`GET /api/invites/{id}/participants`), and the check of all
their completion codes at once (`POST /api/invites/verify-codes`), against its size.

For each --participants count a fresh SQLite queue database (in a temporary folder) gets one
human-taught run with an invite (target 2 answers), joined by that many participants in mixed
states: a third answered nothing, a third one pair, a third two (their target); every fifth is
paused by check pairs. The list (`crowdstudy.participants.participants`) is made once to warm
up (it records the completions it finds), then timed --repeats times, and so is the check of
every participant's code (`crowdstudy.participants.verify_codes`); a table for each gives the
median wall and CPU ms per call, the CPU ms per participant (or code), and the SQL statements
one call runs (which the machine's load does not move).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_participants.py
    PYTHONPATH=. .venv/bin/python benchmarks/bench_participants.py --participants 20 200 1000
    PYTHONPATH=$OLDER_TREE .venv/bin/python benchmarks/bench_participants.py

PYTHONPATH names the checkout whose packages are measured.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

from bench_label_api import query_spec
from sqlalchemy import Engine, event
from sqlalchemy.orm import Session

from crowdstudy.invites import create_invite, join_invite
from crowdstudy.participants import participants, verify_codes
from labelqueue import (
    LabellerPause,
    claim_run,
    create_run,
    lease_next_query,
    make_engine,
    migrate,
    push_queries,
    session_factory,
    submit_label,
)
from labelqueue.models import utcnow


def seed_study(session: Session, people: int) -> int:
    """The study described above; its invite's id."""
    run = create_run(session, name="study", task="dmc:cheetah_run", algo="pebble",
                     budget=4 * people + 10, teacher="human")
    assert claim_run(session, worker_id="bench") is not None
    push_queries(session, run_id=run.id, queries=[
        query_spec(0, i, clips=(f"q{i}-a.mp4", f"q{i}-b.mp4")) for i in range(2 * people)])
    invite = create_invite(session, expires_at=utcnow() + timedelta(days=7), run_id=run.id,
                           target_answers=2, completion_code="BENCH")
    for i in range(people):
        labeller = join_invite(session, code=invite.code, participant=f"p{i}").labeller.id
        for _ in range(i % 3):
            query = lease_next_query(session, labeller_id=labeller, run_id=run.id)
            assert query is not None
            submit_label(session, query_id=query.id, labeller_id=labeller, choice="left",
                         left_is_first=True)
        if i % 5 == 0:
            session.add(LabellerPause(run_id=run.id, labeller_id=labeller, gold_answers=4,
                                      gold_correct=1))
            session.commit()
    return invite.id


def statements(engine: Engine, call: Callable[[], object]) -> int:
    seen: list[str] = []

    def count(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        seen.append(statement)

    event.listen(engine, "before_cursor_execute", count)
    try:
        call()
    finally:
        event.remove(engine, "before_cursor_execute", count)
    return len(seen)


Figures = tuple[float, float, int]
"""median wall ms, median CPU ms and statements of one call"""


def timed(engine: Engine, call: Callable[[], object], repeats: int) -> Figures:
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        call()
        cpus.append(time.process_time() - cpu)
        walls.append(time.perf_counter() - wall)
    return (1000 * statistics.median(walls), 1000 * statistics.median(cpus),
            statements(engine, call))


def measure(people: int, repeats: int) -> tuple[Figures, Figures]:
    """The figures of one list of `people` participants, and of one check of all their
    codes."""
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{Path(tmp) / 'queue.db'}"
        migrate(url)
        engine = make_engine(url)
        try:
            with session_factory(engine)() as session:
                invite_id = seed_study(session, people)
                rows = participants(session, invite_id=invite_id)  # warm-up
                assert len(rows) == people
                codes = [row.completion_code for row in rows]
                listed = timed(engine, lambda: participants(session, invite_id=invite_id),
                               repeats)
                checked = timed(engine, lambda: verify_codes(session, codes), repeats)
        finally:
            engine.dispose()
    return listed, checked


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--participants", type=int, nargs="+", default=[20, 200])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    print(f"{'':>12} {'participants':>12} {'wall ms':>9} {'CPU ms':>9} {'CPU ms each':>12} "
          f"{'statements':>10}")
    for people in args.participants:
        for what, (wall, cpu, count) in zip(("list", "codes"), measure(people, args.repeats),
                                            strict=True):
            print(f"{what:>12} {people:>12} {wall:>9.1f} {cpu:>9.1f} {cpu / people:>12.2f} "
                  f"{count:>10}", flush=True)


if __name__ == "__main__":
    main()

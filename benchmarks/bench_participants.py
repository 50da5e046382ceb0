"""A study's participants list (`GET /api/invites/{id}/participants`) against its size.

For each --participants count a fresh SQLite queue database (in a temporary folder) gets one
human-taught run with an invite (target 2 answers), joined by that many participants in mixed
states: a third answered nothing, a third one pair, a third two (their target); every fifth is
paused by check pairs. The list (`crowdstudy.participants.participants`) is made once to warm
up (it records the completions it finds), then timed --repeats times; the table gives the
median wall and CPU ms per list, the CPU ms per participant, and the SQL statements one list
runs (which the machine's load does not move).

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
from datetime import timedelta
from pathlib import Path
from typing import Any

from bench_label_api import query_spec
from sqlalchemy import Engine, event
from sqlalchemy.orm import Session

from crowdstudy.invites import create_invite, join_invite
from crowdstudy.participants import participants
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


def statements(engine: Engine, session: Session, invite_id: int) -> int:
    seen: list[str] = []

    def count(conn: Any, cursor: Any, statement: str, *_: Any) -> None:
        seen.append(statement)

    event.listen(engine, "before_cursor_execute", count)
    try:
        participants(session, invite_id=invite_id)
    finally:
        event.remove(engine, "before_cursor_execute", count)
    return len(seen)


def measure(people: int, repeats: int) -> tuple[float, float, int]:
    """(median wall ms, median CPU ms, statements) of one list of `people` participants."""
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{Path(tmp) / 'queue.db'}"
        migrate(url)
        engine = make_engine(url)
        try:
            with session_factory(engine)() as session:
                invite_id = seed_study(session, people)
                assert len(participants(session, invite_id=invite_id)) == people  # warm-up
                walls, cpus = [], []
                for _ in range(repeats):
                    wall, cpu = time.perf_counter(), time.process_time()
                    participants(session, invite_id=invite_id)
                    cpus.append(time.process_time() - cpu)
                    walls.append(time.perf_counter() - wall)
                count = statements(engine, session, invite_id)
        finally:
            engine.dispose()
    return 1000 * statistics.median(walls), 1000 * statistics.median(cpus), count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--participants", type=int, nargs="+", default=[20, 200])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    print(f"{'participants':>12} {'wall ms':>9} {'CPU ms':>9} {'CPU ms each':>12} "
          f"{'statements':>10}")
    for people in args.participants:
        wall, cpu, count = measure(people, args.repeats)
        print(f"{people:>12} {wall:>9.1f} {cpu:>9.1f} {cpu / people:>12.2f} {count:>10}",
              flush=True)


if __name__ == "__main__":
    main()

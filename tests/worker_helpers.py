"""Builders shared by the tests that drive a worker through the queue database."""

from __future__ import annotations

import csv
import json
import os
import threading
import time
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    SETTLE_SECONDS,
    Label,
    Query,
    Run,
    RunStatus,
    make_engine,
    migrate,
    session_factory,
)
from labelqueue.models import utcnow
from runvocab.answers import click_of_answer
from runvocab.config import build_config
from trainer.clips import ClipConfig
from trainer.feedback import Query as PairQuery
from trainer.loop import TrainingRun
from trainer.trajectories import Trajectory
from trainer.worker import WorkerConfig, run_worker

# Two rounds of 10 pairs in 1000 tiny steps (rounds at 400 and 800), a SAC update every 4
# steps (the updates are most of a tiny run's time).
RUN = {"task": "dmc:cheetah_run", "algo": "pebble", "preset": "tiny", "seed": 0, "budget": 20,
       "teacher_params": {"eps": 0.3},
       "config": {"steps": 1000, "threads": 1, "update_every": 4}}
SCREEN = {answer: click_of_answer(answer, left_is_first=True).value
          for answer in ("first", "second", "equal", "cant_tell", "skip")}
"""a shadow answer as a person shown the first segment on the left would click it"""


def standalone_run(run_dir: Path) -> Path:
    """The same run as RUN, trained without the queue, answered by its scripted teacher."""
    cfg = build_config(RUN["task"], RUN["preset"], {
        "algo": RUN["algo"], "seed": RUN["seed"], "feedback.budget": RUN["budget"],
        "teacher.eps": RUN["teacher_params"]["eps"], **RUN["config"], "run_dir": str(run_dir)})
    TrainingRun(cfg, progress=False).train()
    return run_dir


def database(tmp_path: Path) -> tuple[str, sessionmaker[Session]]:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    return url, session_factory(make_engine(url))


def worker_config(url: str, data_dir: Path, **kw: Any) -> WorkerConfig:
    return WorkerConfig(database_url=url, data_dir=data_dir, once=True, poll_seconds=0.1,
                        heartbeat_seconds=0.2, clip=ClipConfig(width=64, height=64), **kw)


def start_worker(cfg: WorkerConfig) -> threading.Thread:
    thread = threading.Thread(target=run_worker, args=(cfg,), daemon=True)
    thread.start()
    return thread


def wait_for(condition: Callable[[], Any], timeout: float = 120.0, what: str = "") -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what or condition}")


def run_row(sessions: sessionmaker[Session], run_id: int) -> Run:
    with sessions() as session:
        run = session.get(Run, run_id)
        assert run is not None
        session.expunge(run)
        return run


def run_status(sessions: sessionmaker[Session], run_id: int) -> RunStatus:
    return run_row(sessions, run_id).status


def shadow_choices(sessions: sessionmaker[Session], run_id: int) -> dict[int, str]:
    """The scripted teacher's hidden answer of every query of the run, by query id."""
    with sessions() as session:
        rows = session.execute(select(Query.id, Query.shadow_choice).where(Query.run_id == run_id))
        return {query_id: str(choice) for query_id, choice in rows}


def settle_labels(sessions: sessionmaker[Session], run_id: int) -> None:
    """Date the run's unsettled labels back by SETTLE_SECONDS, as if their undo window had
    passed: the worker uses a person's label only then (`labelqueue.undo`)."""
    back = timedelta(seconds=SETTLE_SECONDS)
    with sessions() as session:
        labels = session.scalars(select(Label).join(Query).where(Query.run_id == run_id))
        for label in labels:
            if label.answered_at > utcnow() - back:
                label.answered_at -= back
                if label.shown_at is not None:
                    label.shown_at -= back
        session.commit()


def labels_jsonl(run_dir: Path) -> list[dict]:
    with open(run_dir / "labels.jsonl") as f:
        return [json.loads(line) for line in f]


def decisions(run_dir: Path) -> list[tuple]:
    """What a run learned from, label by label: which pair, which answer."""
    return [(r["query_id"], r["trajectory0"], r["start0"], r["trajectory1"], r["start1"],
             r["choice"]) for r in labels_jsonl(run_dir)]


def round_accuracies(run_dir: Path) -> list[str]:
    with open(os.path.join(run_dir, "rounds.csv"), newline="") as f:
        return [row["reward_accuracy"] for row in csv.DictReader(f)]


def cheetah_trajectory(id: int, reward: float, length: int = 60) -> Trajectory:
    """A cheetah trajectory at rest, with a constant true reward (its shapes: the worker keeps
    the episodes queries point into, restoring their states)."""
    return Trajectory(id=id, obs=np.zeros((length, 17), np.float32),
                      actions=np.zeros((length, 6), np.float32),
                      true_rewards=np.full(length, reward, np.float32),
                      states=np.zeros((length, 18)), context=0, success=False)


def round_query(i: int) -> PairQuery:
    """Query i of a round of 20-step segments of trajectories 0 and 1, starting at step i."""
    return PairQuery(query_id=f"r0-{i}", round=0, step=400, trajectory0=0, start0=i,
                     trajectory1=1, start1=i, segment_length=20, segment_return0=20.0,
                     segment_return1=22.0, trajectory_return0=60.0, trajectory_return1=66.0,
                     model_p=0.5, score=0.1, rule="disagreement", shadow_choice="second",
                     distinguishable=True)

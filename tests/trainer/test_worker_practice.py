"""A people-taught run with a practice round gets at least its practice pairs as gold pairs in
every round, whatever its gold rate, so whoever starts labelling has a practice round."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from sqlalchemy import select

from labelqueue import Query, claim_run, create_run, make_engine, migrate, session_factory
from runvocab.config import build_config
from trainer.clips import ClipConfig
from trainer.feedback import Query as PairQuery
from trainer.trajectories import Trajectory, TrajectoryPool
from trainer.worker import QueueHooks, WorkerConfig


def trajectory(id: int, reward: float, length: int = 60) -> Trajectory:
    """A cheetah episode's shapes (the worker keeps the episodes its queries point into)."""
    return Trajectory(id=id, obs=np.zeros((length, 17), np.float32),
                      actions=np.zeros((length, 6), np.float32),
                      true_rewards=np.full(length, reward, np.float32),
                      states=np.zeros((length, 18)), context=0, success=False)


def pair(i: int) -> PairQuery:
    return PairQuery(query_id=f"r0-{i}", round=0, step=400, trajectory0=0, start0=i,
                     trajectory1=1, start1=i, segment_length=20, segment_return0=20.0,
                     segment_return1=22.0, trajectory_return0=60.0, trajectory_return1=66.0,
                     model_p=0.5, score=0.1, rule="disagreement", shadow_choice="second",
                     distinguishable=True)


def test_a_round_pushes_the_practice_pairs_at_a_gold_rate_of_0(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    overrides = {"feedback.practice_pairs": 2, "feedback.segment_length": 20}
    with sessions() as session:
        create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=100,
                   teacher="human", config=overrides)
        run = claim_run(session, worker_id="w")
    assert run is not None
    worker = WorkerConfig(database_url=url, data_dir=tmp_path, worker_id="w",
                          clip=ClipConfig(width=64, height=64))
    hooks = QueueHooks(sessions, run, worker, build_config("dmc:cheetah_run", "tiny", overrides),
                       scripted_labeller_id=0)
    pool = TrajectoryPool(10)
    for t in (trajectory(0, 1.0), trajectory(1, 1.1), trajectory(2, 5.0), trajectory(3, 9.0)):
        pool.add(t)
    folder = worker.clips_root / f"run-{run.id}"  # every clip on disk: nothing is rendered
    folder.mkdir(parents=True)
    for stem in [f"r0-{i}" for i in range(3)] + ["r0-g0", "r0-g1"]:
        for side in (0, 1):
            (folder / f"{stem}-{side}.mp4").write_bytes(b"")

    hooks.round_opened([pair(i) for i in range(3)], pool)
    with sessions() as session:
        gold = session.scalars(select(Query).where(Query.gold.is_(True))).all()
    assert len(gold) == 2
    for q in gold:  # a clear answer: the returns differ widely
        assert abs(q.first_segment_return - q.second_segment_return) > 10

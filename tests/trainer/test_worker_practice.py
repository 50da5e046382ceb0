"""A people-taught run with a practice round gets at least its practice pairs as gold pairs in
every round, whatever its gold rate, so whoever starts labelling has a practice round."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import select
from worker_helpers import cheetah_trajectory, round_query

from labelqueue import Query, claim_run, create_run, make_engine, migrate, session_factory
from runvocab.config import build_config
from trainer.clips import ClipConfig
from trainer.queue_hooks import QueueHooks
from trainer.trajectories import TrajectoryPool
from trainer.worker import WorkerConfig


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
    for t in (cheetah_trajectory(0, 1.0), cheetah_trajectory(1, 1.1),
              cheetah_trajectory(2, 5.0), cheetah_trajectory(3, 9.0)):
        pool.add(t)
    folder = worker.clips_root / f"run-{run.id}"  # every clip on disk: nothing is rendered
    folder.mkdir(parents=True)
    for stem in [f"r0-{i}" for i in range(3)] + ["r0-g0", "r0-g1"]:
        for side in (0, 1):
            (folder / f"{stem}-{side}.mp4").write_bytes(b"")

    hooks.round_opened([round_query(i) for i in range(3)], pool)
    with sessions() as session:
        gold = session.scalars(select(Query).where(Query.gold.is_(True))).all()
    assert len(gold) == 2
    for q in gold:  # a clear answer: the returns differ widely
        assert abs(q.first_segment_return - q.second_segment_return) > 10

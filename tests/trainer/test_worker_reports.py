"""What a worker reports in its heartbeat for the run page and the label page to say why a run
waits: the step its next round opens at and its pace, and for S-EPOA the skill pretraining's
length; the worker's row records its host."""

from __future__ import annotations

import socket

from worker_helpers import RUN, database, run_row, worker_config

from labelqueue import Worker, create_run
from runviews.activity import runs_activity
from trainer.worker import run_worker


def test_the_heartbeat_says_when_the_next_round_opens_and_how_long_pretraining_is(tmp_path):
    url, sessions = database(tmp_path)
    with sessions() as session:
        pebble = create_run(session, name="pebble", teacher="scripted", **RUN)
        sepoa = create_run(session, name="sepoa", teacher="scripted", **RUN | {
            "algo": "sepoa", "config": RUN["config"] | {"steps": 400}})
    assert run_worker(worker_config(url, tmp_path / "data")) == 2

    progress = run_row(sessions, pebble.id).progress
    # The last round opened at 800 (rounds every 400 steps in tiny): the next would be 1200.
    assert progress["next_round_step"] == 1200 and progress["fps"] > 0
    assert progress["steps_per_s"] > 0  # the pace lately, for the next round's estimate
    pretrained = run_row(sessions, sepoa.id).progress
    assert (pretrained["pretraining_step"], pretrained["pretraining_steps"]) == (300, 300)
    with sessions() as session:
        [worker] = session.query(Worker).all()
        session.commit()
        assert worker.host == socket.gethostname() and worker.run_id is None
        [activity] = runs_activity(session, [run_row(sessions, pebble.id)])
    assert activity.phase == "finished"

"""The worker pushes a trainer query as `runvocab.query_fields` declares it: every declared
trainer attribute reaches the queue under its queue name, with the round's position and skills."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from labelqueue import (
    Query,
    claim_run,
    create_run,
    make_engine,
    migrate,
    push_queries,
    session_factory,
)
from runvocab.query_fields import QUERY_FIELDS
from trainer.feedback import Query as PairQuery
from trainer.queue_hooks import queue_fields

# The trainer's own name for a query; the queue gives it an id of its own.
TRAINER_ONLY = {"query_id"}


def test_each_trainer_query_attribute_is_declared_or_the_trainers_own() -> None:
    attributes = {field.name for field in dataclasses.fields(PairQuery)}
    declared = {field.trainer for field in QUERY_FIELDS if field.trainer is not None}
    assert attributes - TRAINER_ONLY == declared, (
        f"declared in runvocab/query_fields.py but not trainer attributes: "
        f"{sorted(declared - attributes)}; trainer attributes declared nowhere: "
        f"{sorted(attributes - TRAINER_ONLY - declared)}")


def test_a_pushed_query_holds_each_declared_trainer_attribute(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    q = PairQuery(query_id="r2-5", round=2, step=np.int64(4000), trajectory0=7, start0=3,
                  trajectory1=8, start1=11, segment_length=25, segment_return0=np.float32(1.5),
                  segment_return1=-2.25, trajectory_return0=40.0, trajectory_return1=38.5,
                  model_p=0.75, score=float("nan"), rule="entropy", shadow_choice="first",
                  distinguishable=np.bool_(False), r_avg=97.5)
    skills = {7: np.array([0.5, -1.0], np.float32), 8: None}
    with sessions() as session:
        run = create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=10)
        assert claim_run(session, worker_id="w") is not None
        [query_id] = push_queries(session, run_id=run.id, queries=[queue_fields(q, 5, skills)])
        stored = session.get(Query, query_id)
    assert stored is not None
    for field in QUERY_FIELDS:
        if field.trainer is None:
            continue
        value = getattr(q, field.trainer)
        expected = None if isinstance(value, float) and value != value else value
        assert getattr(stored, field.name) == expected, field.name
    assert (stored.position, stored.first_skill, stored.second_skill) == (5, [0.5, -1.0], None)
    assert (stored.first_clip, stored.second_clip, stored.gold, stored.needs_labels) == (
        None, None, False, 1)

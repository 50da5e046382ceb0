"""A run's configuration is resolved once, when it is created, and stored with it: a preset
changed later changes no stored run; gold and practice settings come from it, presets included;
a run stored without one (before migration 0015) is resolved as before."""

from __future__ import annotations

import math
from typing import Any

import pytest
from queue_helpers import query_spec
from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from labelqueue import (
    Paused,
    Query,
    Run,
    TeacherKind,
    claim_run,
    create_labeller,
    create_run,
    lease_next_query,
    push_queries,
    read_run,
    set_teacher,
    submit_label,
)
from labelqueue.run_config import run_config
from runvocab.answers import Answer, click_of_answer
from runvocab.config import PRESETS, TASK_PRESETS
from runvocab.names import ConfigError
from runvocab.queued_run import queued_run_config

RUN: dict[str, Any] = {"name": "r", "task": "dmc:cheetah_run", "algo": "pebble", "budget": 100,
                       "preset": "small", "seed": 3}


def forget_resolved(session: Session, run_id: int) -> Run:
    """The run as a run stored before resolved configs were kept."""
    session.execute(update(Run).where(Run.id == run_id).values(resolved_config=None))
    session.commit()
    return read_run(session, run_id=run_id)


def test_a_new_run_stores_the_configuration_it_trains_with(session: Session) -> None:
    run = create_run(session, **RUN, teacher_params={"eps": 0.1},
                     config={"sac.lr": "1e-4", "feedback.gold_rate": 0.25})
    stored = read_run(session, run_id=run.id)
    assert stored.resolved_config is not None
    assert stored.resolved_config["sac"]["hidden_dim"] == PRESETS["small"]["sac.hidden_dim"]
    assert stored.resolved_config["feedback"]["gold_rate"] == 0.25
    assert stored.resolved_config["teacher"]["beta"] == "inf"  # strict JSON keeps no infinity
    expected = queued_run_config(task="dmc:cheetah_run", algo="pebble", preset="small", seed=3,
                                 budget=100, teacher_params={"eps": 0.1},
                                 config={"sac.lr": 1e-4, "feedback.gold_rate": 0.25})
    assert run_config(stored) == expected
    assert math.isinf(run_config(stored).teacher.beta)


def test_a_run_no_worker_could_train_is_refused_and_not_stored(session: Session) -> None:
    with pytest.raises(ConfigError, match="reward.surf"):
        create_run(session, **RUN, config={"reward.surf": "flase"})
    with pytest.raises(ConfigError, match="feedback.budget"):
        create_run(session, **RUN, config={"feedback.budget": 7})  # budget says 100
    assert claim_run(session, worker_id="w") is None


def test_a_preset_changed_after_enqueue_changes_no_stored_run(
        session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    run = create_run(session, **RUN)
    monkeypatch.setitem(PRESETS, "small", PRESETS["small"] | {"sac.hidden_dim": 64})
    assert run_config(read_run(session, run_id=run.id)).sac.hidden_dim == 256
    # A run stored without its configuration is resolved as before: against today's presets.
    assert run_config(forget_resolved(session, run.id)).sac.hidden_dim == 64


def test_a_new_teacher_changes_the_stored_teacher_and_nothing_else(
        session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    run = create_run(session, **RUN, teacher_params={"eps": 0.1, "eps_skip": 0.2})
    monkeypatch.setitem(PRESETS, "small", PRESETS["small"] | {"sac.hidden_dim": 64})
    set_teacher(session, run_id=run.id, teacher="scripted", params={"eps": 0.3})
    cfg = run_config(read_run(session, run_id=run.id))
    assert (cfg.teacher.eps, cfg.teacher.eps_skip, cfg.sac.hidden_dim) == (0.3, 0.0, 256)
    with pytest.raises(ConfigError, match="teacher.eps"):
        set_teacher(session, run_id=run.id, teacher="scripted", params={"eps": "lots"})
    assert run_config(read_run(session, run_id=run.id)).teacher.eps == 0.3


def paused_by_a_wrong_gold_answer(session: Session, run: Run) -> bool:
    """Claim the run, push a gold pair and ordinary queries, and answer what comes, the gold
    pair wrongly; whether that paused the labeller on the run."""
    claimed = claim_run(session, worker_id=f"w{run.id}")
    assert claimed is not None and claimed.id == run.id
    specs = [query_spec(i, gold=i % 3 == 1) for i in range(24)]  # served in their order
    ids = push_queries(session, run_id=run.id, queries=specs)
    gold = {i for i, spec in zip(ids, specs, strict=True) if spec.get("gold")}
    ann, _ = create_labeller(session, name=f"ann-{run.id}")
    for _ in ids:
        try:
            query = lease_next_query(session, labeller_id=ann.id, run_id=run.id)
        except Paused:
            return True
        if query is None:
            return False
        answer = Answer.FIRST if query.id in gold else Answer.SECOND  # gold: wrong
        submit_label(session, query_id=query.id, labeller_id=ann.id, left_is_first=True,
                     choice=click_of_answer(answer, left_is_first=True))
    return False


GOLD_PRESET = {"feedback.gold_rate": 0.5, "feedback.gold_min_accuracy": 0.5,
               "feedback.gold_min_answers": 1}


def test_gold_settings_a_preset_gives_are_honoured(
        session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(TASK_PRESETS, "dmc:cheetah_run",
                        TASK_PRESETS["dmc:cheetah_run"] | GOLD_PRESET)
    run = create_run(session, **RUN, teacher=TeacherKind.HUMAN)
    monkeypatch.undo()  # the stored run keeps them
    assert paused_by_a_wrong_gold_answer(session, run)
    plain = create_run(session, **RUN | {"name": "plain"}, teacher=TeacherKind.HUMAN)
    assert not paused_by_a_wrong_gold_answer(session, plain)  # no gold pair served


def test_a_run_stored_without_its_configuration_takes_gold_settings_from_its_overrides(
        session: Session) -> None:
    run = create_run(session, **RUN, teacher=TeacherKind.HUMAN, config=GOLD_PRESET)
    assert paused_by_a_wrong_gold_answer(session, forget_resolved(session, run.id))


def test_practice_pairs_a_preset_gives_are_honoured(
        session: Session, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(TASK_PRESETS, "dmc:cheetah_run",
                        TASK_PRESETS["dmc:cheetah_run"] | {"feedback.practice_pairs": 2})
    run = create_run(session, **RUN, teacher=TeacherKind.HUMAN)
    monkeypatch.undo()
    old = create_run(session, **RUN | {"name": "old"}, teacher=TeacherKind.HUMAN,
                     config={"feedback.practice_pairs": 3})
    forget_resolved(session, old.id)
    for run_id, reserved in ((run.id, 2), (old.id, 3)):
        push_queries(session, run_id=run_id, queries=[query_spec(i, gold=True) for i in range(5)])
        practice = session.scalar(select(func.count()).select_from(Query).where(
            Query.run_id == run_id, Query.practice.is_(True)))
        session.commit()
        assert practice == reserved

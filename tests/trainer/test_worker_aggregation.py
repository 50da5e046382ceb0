"""The worker takes a query as answered when k people answered it (or the scripted teacher did),
trains on their majority, and pushes each query wanting k answers and gold pairs wanting all."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select
from worker_helpers import cheetah_trajectory, round_query

import trainer.queue_hooks as hooks_module
from labelqueue import (
    GOLD_NEEDS_LABELS,
    Label,
    LabelSource,
    Query,
    claim_run,
    create_labeller,
    create_run,
    export_rows,
    labels_for_queries,
    lease_next_query,
    make_engine,
    migrate,
    push_queries,
    session_factory,
    set_teacher,
    submit_answer,
    submit_label,
)
from runvocab.answers import Answer
from runvocab.config import build_config
from trainer.clips import ClipConfig
from trainer.queue_hooks import QueueHooks, _answer, complete_queries
from trainer.trajectories import TrajectoryPool
from trainer.worker import WorkerConfig, scripted_labeller_id

T0 = datetime(2026, 11, 23, 12, 0, tzinfo=UTC)
NAMES = {1: "ann", 2: "bob", 3: "cy", 9: "scripted-teacher"}


def label(query_id: int, labeller_id: int, answer: Answer, *, seconds: int = 0,
          source: LabelSource = LabelSource.HUMAN) -> Label:
    return Label(query_id=query_id, run_id=1, labeller_id=labeller_id, answer=answer,
                 source=source, answered_at=T0 + timedelta(seconds=seconds))


def test_a_query_is_complete_with_k_answers_or_the_scripted_teachers() -> None:
    labels = [
        label(10, 1, Answer.FIRST), label(10, 2, Answer.SECOND), label(10, 3, Answer.SKIP),
        label(11, 1, Answer.FIRST), label(11, 2, Answer.FIRST),
        label(12, 9, Answer.SECOND, source=LabelSource.SCRIPTED),
    ]
    assert complete_queries(labels, 3) == {10, 12}
    assert complete_queries(labels, 2) == {10, 11, 12}
    assert complete_queries(labels, 1) == {10, 11, 12}
    assert complete_queries([], 3) == set()


@pytest.mark.parametrize(
    ("answers", "expected"),
    [
        ([Answer.FIRST, Answer.SECOND, Answer.FIRST], Answer.FIRST),
        ([Answer.SECOND, Answer.SECOND, Answer.EQUAL], Answer.SECOND),
        ([Answer.FIRST, Answer.SECOND], Answer.CANT_TELL),
        ([Answer.CANT_TELL, Answer.CANT_TELL, Answer.FIRST], Answer.CANT_TELL),
        ([Answer.SKIP, Answer.EQUAL, Answer.SKIP], Answer.EQUAL),
        ([Answer.SKIP, Answer.SKIP, Answer.SKIP], Answer.SKIP),
    ],
)
def test_the_trained_answer_is_the_peoples_majority(answers: list[Answer],
                                                     expected: Answer) -> None:
    given = [label(10, i + 1, a, seconds=10 - i) for i, a in enumerate(answers)]
    out = _answer(given, NAMES)
    assert out.choice is expected
    assert out.labeller == "+".join(NAMES[i + 1] for i in range(len(answers)))
    assert out.source == "human"
    assert out.answered_at == (T0 + timedelta(seconds=10)).timestamp()  # the latest answer


def test_the_scripted_teachers_answer_decides_over_peoples() -> None:
    given = [label(10, 1, Answer.FIRST), label(10, 2, Answer.FIRST),
             label(10, 9, Answer.SECOND, seconds=3, source=LabelSource.SCRIPTED)]
    out = _answer(given, NAMES)
    assert (out.choice, out.labeller, out.source) == (Answer.SECOND, "scripted-teacher",
                                                      "scripted")
    assert out.answered_at == (T0 + timedelta(seconds=3)).timestamp()


# (people's answers, then the scripted teacher's or None): each one run's only query, k = 3
MIXED = [
    (["first", "first"], "second"),  # two people, then the teacher, who decides
    (["cant_tell", "cant_tell"], "first"),
    (["first"], "cant_tell"),
    ([], "equal"),
    (["second", "first", "first"], None),  # people only: their majority
    (["first", "second", "skip"], None),
]


def test_the_exports_aggregate_is_what_the_trainer_trains_on(tmp_path: Path) -> None:
    """A query people answered before the operator switched the run to the scripted teacher
    is trained on the teacher's answer alone: the export's `aggregate` says the same answer as
    the trainer's own rule, query by query."""
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    scripted = scripted_labeller_id(sessions)
    query_ids = []
    with sessions() as session:
        people = [create_labeller(session, name=n)[0].id for n in ("ann", "bob", "cy")]
        for i, (answers, teacher_says) in enumerate(MIXED):
            run = create_run(session, name=f"r{i}", task="dmc:cheetah_run", algo="pebble",
                             budget=100, config={"feedback.labels_per_query": 3})
            assert claim_run(session, worker_id=f"w{i}") is not None
            [query_id] = push_queries(session, run_id=run.id, queries=[{
                "round": 0, "position": 0, "step": 1000, "segment_length": 50,
                "first_trajectory": 0, "first_start": 10, "second_trajectory": 1,
                "second_start": 20, "first_segment_return": 1.5, "second_segment_return": 2.5,
                "first_clip": "q-a.mp4", "second_clip": "q-b.mp4", "needs_labels": 3}])
            for person, answer in zip(people, answers, strict=False):
                leased = lease_next_query(session, labeller_id=person, run_id=run.id)
                assert leased is not None and leased.id == query_id
                submit_label(session, query_id=query_id, labeller_id=person,
                             choice={"first": "left", "second": "right"}.get(answer, answer),
                             left_is_first=True)
            if teacher_says is not None:
                set_teacher(session, run_id=run.id, teacher="scripted", params={})
                leased = lease_next_query(session, labeller_id=scripted, run_id=run.id)
                assert leased is not None and leased.id == query_id
                submit_answer(session, query_id=query_id, labeller_id=scripted,
                              answer=teacher_says)
            query_ids.append(query_id)
        exported = {(row["query_id"], row["aggregate"]) for row in export_rows(session)}
        trained = {(q, _answer(labels_for_queries(session, query_ids=[q]), NAMES).choice.value)
                   for q in query_ids}
    assert exported == trained
    assert dict(exported)[query_ids[0]] == "second"  # not the people's majority


def test_a_labeller_without_a_name_is_named_by_id() -> None:
    assert _answer([label(10, 7, Answer.EQUAL)], {}).labeller == "labeller-7"


@pytest.mark.parametrize("teacher", ["human", "scripted"])
def test_a_round_is_pushed_wanting_k_answers_and_gold_pairs_wanting_all(
    tmp_path: Path, teacher: str
) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    overrides = {"feedback.labels_per_query": 3, "feedback.gold_rate": 0.25,
                 "feedback.segment_length": 20}
    with sessions() as session:
        create_run(session, name="r", task="dmc:cheetah_run", algo="pebble", budget=100,
                   teacher=teacher, config=overrides)
        run = claim_run(session, worker_id="w")
    assert run is not None
    worker = WorkerConfig(database_url=url, data_dir=tmp_path, worker_id="w",
                          clip=ClipConfig(width=64, height=64))
    cfg = build_config("dmc:cheetah_run", "tiny", overrides)
    hooks = QueueHooks(sessions, run, worker, cfg, scripted_labeller_id=0)
    trajectories = TrajectoryPool(10)
    for t in (cheetah_trajectory(0, 1.0), cheetah_trajectory(1, 1.1),
              cheetah_trajectory(2, 5.0)):
        trajectories.add(t)
    # Every clip already on disk, so nothing is rendered.
    folder = worker.clips_root / f"run-{run.id}"
    folder.mkdir(parents=True)
    for stem in [f"r0-{i}" for i in range(4)] + ["r0-g0", "r0-g1"]:
        for side in (0, 1):
            (folder / f"{stem}-{side}.mp4").write_bytes(b"")

    hooks.round_opened([round_query(i) for i in range(4)], trajectories)
    with sessions() as session:
        stored = session.scalars(select(Query).order_by(Query.position)).all()
        rows = [(q.gold, q.needs_labels) for q in stored]
    if teacher == "human":  # 4 queries at rate 0.25: two gold pairs, at places among them
        assert sorted(rows) == [(False, 3)] * 4 + [(True, GOLD_NEEDS_LABELS)] * 2
        gold, _ = [q for q in stored if q.gold]
        assert 2 in (gold.first_trajectory, gold.second_trajectory)
    else:  # the scripted teacher is not measured
        assert rows == [(False, 3)] * 4


def test_two_workers_answering_as_the_scripted_teacher_at_once_lose_no_query(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Both workers answer as one scripted labeller, and a labeller's lease for one run releases
    its lease for another: a lease taken away between lease and submit is leased again."""
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    migrate(url)
    sessions = session_factory(make_engine(url))
    overrides = {"feedback.segment_length": 20}
    cfg = build_config("dmc:cheetah_run", "tiny", overrides)
    trajectories = TrajectoryPool(10)
    for t in (cheetah_trajectory(0, 1.0), cheetah_trajectory(1, 1.1)):
        trajectories.add(t)
    scripted = scripted_labeller_id(sessions)
    hooks = []
    for name in ("w0", "w1"):
        with sessions() as session:
            create_run(session, name=name, task="dmc:cheetah_run", algo="pebble", budget=100,
                       teacher="scripted", config=overrides)
            run = claim_run(session, worker_id=name)
        assert run is not None
        worker = WorkerConfig(database_url=url, data_dir=tmp_path, worker_id=name,
                              clip=ClipConfig(width=64, height=64))
        hooks.append(QueueHooks(sessions, run, worker, cfg, scripted_labeller_id=scripted))
        hooks[-1].round_opened([round_query(i) for i in range(4)], trajectories)
    first, second = hooks

    real_submit = hooks_module.submit_answer
    stolen: list[int] = []

    def submit_after_the_other_worker_leased(session, **kw):  # type: ignore[no-untyped-def]
        if len(stolen) < 3:  # the other worker leases for its run just before this submit
            with sessions() as other:
                leased = lease_next_query(other, labeller_id=scripted, run_id=second.run_id,
                                          gold=False)
            assert leased is not None
            stolen.append(kw["query_id"])
        return real_submit(session, **kw)

    monkeypatch.setattr(hooks_module, "submit_answer", submit_after_the_other_worker_leased)
    first._answer_as_scripted([round_query(i) for i in range(4)])
    monkeypatch.setattr(hooks_module, "submit_answer", real_submit)
    second._answer_as_scripted([round_query(i) for i in range(4)])

    assert len(stolen) == 3 and len(set(stolen)) == 1  # the same query lost three times
    with sessions() as session:
        answered = session.execute(select(Label.run_id, Label.query_id)).all()
    for h in hooks:
        ids = sorted(q for r, q in answered if r == h.run_id)
        assert ids == sorted(h.query_ids.values())  # every query answered, none twice

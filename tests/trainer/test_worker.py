"""The worker trains runs from the queue database and obeys operators; a scripted teacher and a
person answer through the same queue operations, and the run learns the same either way."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from sqlalchemy import func, select
from worker_helpers import (
    RUN,
    SCREEN,
    database,
    decisions,
    labels_jsonl,
    round_accuracies,
    run_row,
    run_status,
    settle_labels,
    shadow_choices,
    standalone_run,
    start_worker,
    wait_for,
    worker_config,
)

from labelqueue import (
    Label,
    Labeller,
    MetricStream,
    Query,
    QueryStatus,
    RunStatus,
    create_labeller,
    create_run,
    lease_next_query,
    read_metrics,
    set_run_status,
    set_teacher,
    submit_label,
)
from trainer.worker import run_worker


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    return standalone_run(tmp_path_factory.mktemp("reference") / "run")


def test_a_scripted_run_through_the_queue_learns_what_a_standalone_run_learns(tmp_path,
                                                                               reference):
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="scripted", teacher="scripted", **RUN)
    assert run_worker(worker_config(url, tmp_path / "data")) == 1

    done = run_row(sessions, run.id)
    assert done.status is RunStatus.FINISHED and done.step == 1000 and done.labels_used == 20
    with sessions() as session:
        sources = session.execute(
            select(Labeller.name, Label.source, func.count()).join(Labeller)
            .group_by(Labeller.name, Label.source)).all()
        statuses = set(session.scalars(select(Query.status)))
        rounds = read_metrics(session, run_id=run.id, stream=MetricStream.ROUNDS)
    assert sources == [("scripted-teacher", "scripted", 20)]
    assert statuses == {QueryStatus.LABELLED}
    run_dir = tmp_path / "data" / "runs" / f"run-{run.id}"
    assert decisions(run_dir) == decisions(reference)
    assert round_accuracies(run_dir) == round_accuracies(reference)
    # The dashboard's curves are in the database, the same as the run's own files.
    assert [r.values["labels_used"] for r in rounds] == [10, 20]
    assert [str(r.values["reward_accuracy"]) for r in rounds] == round_accuracies(reference)


def test_operator_pauses_a_waiting_run_and_hands_it_to_the_scripted_teacher(tmp_path,
                                                                             reference):
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="people", teacher="human", **RUN)
    thread = start_worker(worker_config(url, tmp_path / "data"))

    # Nobody labels: the worker waits.
    wait_for(lambda: _rendered(sessions, run.id) == 10, what="round 0's clips")
    with sessions() as session:
        set_run_status(session, run_id=run.id, status=RunStatus.PAUSED)
        set_teacher(session, run_id=run.id, teacher="scripted", params={"eps": 0.3})
        set_run_status(session, run_id=run.id, status=RunStatus.RUNNING)
    thread.join(timeout=120)
    assert not thread.is_alive()
    assert run_status(sessions, run.id) is RunStatus.FINISHED
    run_dir = tmp_path / "data" / "runs" / f"run-{run.id}"
    assert decisions(run_dir) == decisions(reference)
    clips = sorted(p.name for p in (tmp_path / "data" / "clips" / f"run-{run.id}").glob("*.mp4"))
    assert clips == sorted(f"r0-q{i}-{s}.mp4" for i in range(10) for s in (0, 1))


def test_a_stopped_run_checkpoints_and_a_requeued_one_resumes_to_the_same_result(tmp_path,
                                                                                 reference):
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="stop", teacher="scripted", **RUN)
    thread = start_worker(worker_config(url, tmp_path / "data"))
    wait_for(lambda: run_row(sessions, run.id).step >= 300, what="step 300")
    with sessions() as session:
        set_run_status(session, run_id=run.id, status=RunStatus.STOPPING)
    thread.join(timeout=60)
    stopped = run_row(sessions, run.id)
    assert stopped.status is RunStatus.STOPPED and stopped.step % 200 == 0  # an episode's end
    assert 300 <= stopped.step < 1000

    with sessions() as session:
        set_run_status(session, run_id=run.id, status=RunStatus.QUEUED)
    run_worker(worker_config(url, tmp_path / "data"))
    assert run_status(sessions, run.id) is RunStatus.FINISHED
    run_dir = tmp_path / "data" / "runs" / f"run-{run.id}"
    assert decisions(run_dir) == decisions(reference)
    assert round_accuracies(run_dir) == round_accuracies(reference)


def _rendered(sessions, run_id: int) -> int:
    with sessions() as session:
        return session.scalar(select(func.count()).where(
            Query.run_id == run_id, Query.second_clip.is_not(None))) or 0


def _label_as_person(sessions, labeller_id: int, run_id: int, limit: int) -> int:
    """Answer up to `limit` open queries of the run as a person would: the shadow answer,
    dated back past the undo window so the worker need not wait it out."""
    given = 0
    while given < limit:
        with sessions() as session:
            query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id)
            if query is None:
                return given
            choice = SCREEN[shadow_choices(sessions, run_id)[query.id]]
            submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=choice,
                         left_is_first=True)
        settle_labels(sessions, run_id)
        given += 1
    return given


def test_a_killed_worker_resumes_and_no_label_is_lost_or_used_twice(tmp_path, reference):
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="people", teacher="human", **RUN)
        person, _ = create_labeller(session, name="alice")
    data = tmp_path / "data"
    command = [sys.executable, "-m", "sepoa", "worker", "--database-url", url,
               "--data-dir", str(data), "--worker-id", "w1", "--once", "--poll-seconds", "0.1",
               "--clip-size", "64"]
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    worker = subprocess.Popen(command, env=env)
    try:
        # Half of round 0, then the worker dies while it waits for the rest.
        wait_for(lambda: _rendered(sessions, run.id) == 10, what="round 0's clips")
        assert _label_as_person(sessions, person.id, run.id, 5) == 5
        worker.send_signal(signal.SIGKILL)
        worker.wait()
        # People go on labelling while no worker runs.
        _label_as_person(sessions, person.id, run.id, 5)
        assert run_row(sessions, run.id).labels_used == 10
    finally:
        if worker.poll() is None:
            worker.kill()

    stop = threading.Event()

    def keep_labelling() -> None:
        while not stop.is_set():
            if not _label_as_person(sessions, person.id, run.id, 10):
                stop.wait(0.1)

    labeller = threading.Thread(target=keep_labelling, daemon=True)
    labeller.start()
    try:  # a worker of the same id, here in-process: it takes the run back
        assert run_worker(worker_config(url, data, worker_id="w1")) == 1
    finally:
        stop.set()
        labeller.join()

    assert run_status(sessions, run.id) is RunStatus.FINISHED
    run_dir = data / "runs" / f"run-{run.id}"
    logged = labels_jsonl(run_dir)
    with sessions() as session:
        stored = session.scalar(select(func.count()).select_from(Label))
    assert stored == 20 and len(logged) == 20
    assert len({row["query_id"] for row in logged}) == 20  # each label used once
    assert {row["labeller"] for row in logged} == {"alice"}
    assert {row["source"] for row in logged} == {"human"}
    assert decisions(run_dir) == decisions(reference)
    assert round_accuracies(run_dir) == round_accuracies(reference)

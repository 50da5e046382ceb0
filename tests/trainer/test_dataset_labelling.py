"""Labelling an existing dataset: a labelling-only run over a small dataset export, served by a
real worker (clips rendered from the dataset's stored states), answered by a programmatic
labeller through the queue as a person's answers go, its second round drawn by the disagreement
of the ensemble refitted on the first round's labels; both exports point at the dataset's
episodes."""

from __future__ import annotations

import json
import threading
import time

import imageio.v2 as imageio
import numpy as np
import pandas as pd
import pytest
from labelling_helpers import exported_dataset
from sqlalchemy import select
from worker_helpers import (
    database,
    labels_jsonl,
    run_row,
    settle_labels,
    start_worker,
    wait_for,
    worker_config,
)

from labelqueue import (
    Query,
    RunStatus,
    create_labeller,
    export_rows,
    lease_next_query,
    set_run_status,
    submit_label,
)
from rundata.dataset import read_dataset, write_dataset
from rundata.labelling import create_labelling_run
from trainer.clips import ClipConfig, encode_mp4, iter_segment_frames, sized
from trainer.envs import make_env
from trainer.reward_fit import fit

BUDGET, PER_ROUND, SEGMENT = 12, 6, 20


def _segment_return(dataset, episode: int, start: int) -> float:
    return float(dataset.episodes[episode].rewards[start:start + SEGMENT].sum(dtype=np.float64))


def _label_as_a_person(sessions, run_id: int, labeller_id: int, dataset, done: threading.Event,
                       answered: list[int], limit: int | None = None) -> None:
    """A labeller who leases rendered pairs as the label page does and prefers the segment
    with the larger return (equal ones are equal), read from the dataset at the pair's
    pointers (not from the query's hidden truth); until `done`, or `limit` answers."""
    while not done.is_set() and (limit is None or len(answered) < limit):
        with sessions() as session:
            query = lease_next_query(session, labeller_id=labeller_id, run_id=run_id,
                                     for_people=True)
            if query is None:
                time.sleep(0.05)
                continue
            first = _segment_return(dataset, query.first_trajectory, query.first_start)
            second = _segment_return(dataset, query.second_trajectory, query.second_start)
            choice = "left" if first > second else "right" if second > first else "equal"
            submit_label(session, query_id=query.id, labeller_id=labeller_id, choice=choice,
                         left_is_first=True)
        settle_labels(sessions, run_id)  # as if the undo window had passed
        answered.append(query.id)


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("labelling")
    path = exported_dataset(tmp / "datasets")
    dataset = read_dataset(str(path))
    url, sessions = database(tmp)
    with sessions() as session:
        run = create_labelling_run(session, dataset=str(path), budget=BUDGET,
                                   per_round=PER_ROUND, selection="disagreement",
                                   preset="tiny", clip_size="128x128",
                                   config={"threads": 1})
        alice, _token = create_labeller(session, name="alice")
    data = tmp / "data"
    done, answered = threading.Event(), []
    person = threading.Thread(target=_label_as_a_person,
                              args=(sessions, run.id, alice.id, dataset, done, answered),
                              daemon=True)
    person.start()
    worker = start_worker(worker_config(url, data))
    worker.join(timeout=300)
    done.set()
    person.join(timeout=10)
    assert not worker.is_alive()
    with sessions() as session:
        queries = list(session.scalars(select(Query).where(Query.run_id == run.id)
                                       .order_by(Query.id)))
        session.expunge_all()
        rows = list(export_rows(session, run_id=run.id))
    return {"tmp": tmp, "path": path, "dataset": dataset, "sessions": sessions,
            "run": run_row(sessions, run.id), "data": data, "queries": queries, "rows": rows,
            "answered": answered}


def test_the_run_serves_rounds_until_its_budget_is_spent_then_finishes(labelled):
    run = labelled["run"]
    assert run.status is RunStatus.FINISHED and run.dataset == str(labelled["path"].resolve())
    assert run.labels_used == BUDGET and len(labelled["answered"]) == BUDGET
    assert [q.round for q in labelled["queries"]] == [0] * PER_ROUND + [1] * PER_ROUND
    run_dir = labelled["data"] / "runs" / f"run-{run.id}"
    done = json.loads((run_dir / "done.json").read_text())
    assert (done["rounds"], done["labels_used"], done["episodes"]) == (2, BUDGET, 4)


def test_pairs_point_into_the_datasets_episodes(labelled):
    dataset = labelled["dataset"]
    for q in labelled["queries"]:
        assert q.first_trajectory != q.second_trajectory
        assert {q.first_trajectory, q.second_trajectory} <= set(range(len(dataset.episodes)))
        assert q.first_segment_return == _segment_return(dataset, q.first_trajectory,
                                                         q.first_start)
        assert q.second_segment_return == _segment_return(dataset, q.second_trajectory,
                                                          q.second_start)


def test_the_second_round_is_drawn_by_the_disagreement_of_the_refitted_ensemble(labelled):
    first, second = labelled["queries"][:PER_ROUND], labelled["queries"][PER_ROUND:]
    assert {q.rule for q in first} == {"uniform"}
    assert all(q.score is None and q.model_p is None for q in first)
    assert {q.rule for q in second} == {"disagreement"}
    assert all(q.score is not None and q.score > 0 for q in second)
    rounds = pd.read_csv(labelled["data"] / "runs" / f"run-{labelled['run'].id}" / "rounds.csv")
    # The ensemble trained after each round, on every label so far.
    assert list(rounds.trained_pairs) == [PER_ROUND, 2 * PER_ROUND]
    assert (rounds.reward_epochs > 0).all()


def test_clips_are_rendered_from_the_datasets_stored_states(labelled, tmp_path):
    run, dataset = labelled["run"], labelled["dataset"]
    clip = sized(ClipConfig(width=64, height=64), run.clip_size)  # as the worker's
    clips = labelled["data"] / "clips"
    env = make_env("dmc:cheetah_run", 7)
    for q in (labelled["queries"][0], labelled["queries"][-1]):
        for side, key in (("first", q.first_clip), ("second", q.second_clip)):
            episode = dataset.episodes[getattr(q, f"{side}_trajectory")]
            frames = iter_segment_frames(env, episode.states, episode.context,
                                         getattr(q, f"{side}_start"), SEGMENT, clip)
            again = encode_mp4(frames, tmp_path / f"{q.id}-{side}.mp4", clip)
            shown, rendered = (_decode(p) for p in (clips / key, again))
            assert shown.shape == (SEGMENT, 128, 128, 3)
            np.testing.assert_array_equal(shown, rendered)


def _decode(path) -> np.ndarray:
    with imageio.get_reader(path) as reader:
        return np.stack(list(reader.iter_data()))


def test_the_label_export_points_at_the_datasets_episodes(labelled):
    rows, dataset = labelled["rows"], labelled["dataset"]
    assert len(rows) == BUDGET and {r["labeller_name"] for r in rows} == {"alice"}
    for row in rows:
        for side in ("first", "second"):
            episode, start = row[f"{side}_trajectory"], row[f"{side}_start"]
            assert row[f"{side}_segment_return"] == _segment_return(dataset, episode, start)
        # The labeller preferred the larger return: every answer is correct.
        assert row["correct"] is True


def test_the_runs_dataset_export_holds_the_labelled_episodes(labelled):
    with labelled["sessions"]() as session:
        summary = write_dataset(session, run_id=labelled["run"].id,
                                clips_root=labelled["data"] / "clips",
                                root=labelled["tmp"] / "labelled")
    again, source = read_dataset(str(summary.path)), labelled["dataset"]
    assert again.info["source_dataset"] == str(labelled["path"].resolve())
    episodes = pd.read_parquet(summary.path / "episodes.parquet")
    # Each exported episode is the source dataset's episode its `trajectory` names.
    for i, trajectory in enumerate(episodes.trajectory):
        e, s = again.episodes[i], source.episodes[int(trajectory)]
        np.testing.assert_array_equal(e.observations, s.observations)
        np.testing.assert_array_equal(e.states, s.states)
        np.testing.assert_array_equal(e.rewards, s.rewards)
    assert len(again.queries) == BUDGET
    for q in again.queries:
        t = int(episodes.trajectory[q["first_episode"]])
        assert q["first_segment_return"] == _segment_return(source, t, q["first_start"])
    # An offline fit takes it as it takes a training run's export.
    result = fit(again, holdout=0.25, seed=0)
    assert result.metrics["pairs"] == BUDGET and result.metrics["heldout_pairs"] == 3



def test_a_stopped_labelling_run_resumes_its_open_round_when_requeued(tmp_path):
    path = exported_dataset(tmp_path / "datasets", seed=1)
    dataset = read_dataset(str(path))
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_labelling_run(session, dataset=str(path), budget=8, per_round=4,
                                   preset="tiny", config={"threads": 1})
        bob, _token = create_labeller(session, name="bob")
    data, answered = tmp_path / "data", []
    worker = start_worker(worker_config(url, data))
    # Two of round 0's four pairs answered, then the operator stops the run.
    _label_as_a_person(sessions, run.id, bob.id, dataset, threading.Event(), answered, limit=2)
    with sessions() as session:
        set_run_status(session, run_id=run.id, status=RunStatus.STOPPING)
    worker.join(timeout=60)
    assert run_row(sessions, run.id).status is RunStatus.STOPPED

    with sessions() as session:
        set_run_status(session, run_id=run.id, status=RunStatus.QUEUED)
    done = threading.Event()
    person = threading.Thread(target=_label_as_a_person, daemon=True,
                              args=(sessions, run.id, bob.id, dataset, done, answered))
    person.start()
    worker = start_worker(worker_config(url, data))
    worker.join(timeout=120)
    done.set()
    person.join(timeout=10)
    finished = run_row(sessions, run.id)
    assert finished.status is RunStatus.FINISHED and finished.labels_used == 8
    with sessions() as session:  # round 0 was pushed again, not asked twice
        rounds = list(session.scalars(select(Query.round).where(Query.run_id == run.id)))
    assert sorted(rounds) == [0] * 4 + [1] * 4
    logged = labels_jsonl(data / "runs" / f"run-{run.id}")
    assert len({row["query_id"] for row in logged}) == len(logged) == 8
    wait_for(lambda: len(answered) == 8, what="every answer")


def test_the_scripted_teacher_labels_a_dataset_from_its_true_rewards(tmp_path):
    path = exported_dataset(tmp_path / "datasets", seed=2)
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_labelling_run(session, dataset=str(path), budget=9, per_round=3,
                                   preset="tiny", teacher="scripted",
                                   config={"threads": 1, "teacher.eps": 0.0})
    start_worker(worker_config(url, tmp_path / "data")).join(timeout=120)
    assert run_row(sessions, run.id).status is RunStatus.FINISHED
    with sessions() as session:
        rows = list(export_rows(session, run_id=run.id))
        rendered = session.scalars(select(Query.first_clip).where(Query.run_id == run.id))
        assert set(rendered) == {None}  # nobody watches: no clip is rendered
    assert [r["round"] for r in rows] == [0] * 3 + [1] * 3 + [2] * 3
    assert {r["source"] for r in rows} == {"scripted"}
    assert all(r["answer"] == r["shadow_choice"] for r in rows)
    assert all(r["correct"] for r in rows if r["answer"] in ("first", "second"))

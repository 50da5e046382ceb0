"""A run's data as a Minari dataset: a tiny run through the worker, exported with
`sepoa export --dataset`, read back with Minari, and compared with the run's own checkpoint and
the clips its labellers were shown."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pandas as pd
import pytest
from sqlalchemy import func, select
from worker_helpers import (
    RUN,
    database,
    run_row,
    run_status,
    start_worker,
    wait_for,
    worker_config,
)

from labelqueue import Query, RunStatus, create_run, set_run_status, set_teacher
from sepoa.cli import main
from trainer.checkpoint import load_checkpoint
from trainer.clips import ClipConfig, encode_mp4, iter_segment_frames, sized
from trainer.envs import make_env

DATASET_ID = "sepoa/dmc-cheetah_run/run-1-v0"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished run (two rounds of 10 queries on 200-step episodes) and its export. People
    teach round 0, so its clips are rendered; nobody answers, and the operator hands the run to
    the scripted teacher, who answers everything."""
    tmp = tmp_path_factory.mktemp("dataset")
    url, sessions = database(tmp)
    with sessions() as session:
        create_run(session, name="tiny", teacher="human", clip_size="128x128", **RUN)
    data = tmp / "data"
    thread = start_worker(worker_config(url, data))
    wait_for(lambda: _rendered(sessions) == 10, what="round 0's clips")
    with sessions() as session:
        set_run_status(session, run_id=1, status=RunStatus.PAUSED)
        set_teacher(session, run_id=1, teacher="scripted", params={"eps": 0.3})
        set_run_status(session, run_id=1, status=RunStatus.RUNNING)
    thread.join(timeout=300)
    assert run_status(sessions, 1) is RunStatus.FINISHED
    with sessions() as session:  # queued, never trained: no episodes
        create_run(session, name="untrained", teacher="scripted", **RUN)
    roots = tmp / "datasets"
    args = ["export", "--database-url", url, "--data-dir", str(data), "--dataset", str(roots),
            "--run", "1"]
    assert main(args) == 0
    return {"url": url, "data": data, "roots": roots, "args": args,
            "path": roots / DATASET_ID, "run_dir": data / "runs" / "run-1",
            "clip_size": run_row(sessions, 1).clip_size}


def _rendered(sessions) -> int:
    with sessions() as session:
        return session.scalar(select(func.count()).where(
            Query.run_id == 1, Query.second_clip.is_not(None))) or 0


def _load(trained):
    import minari

    os.environ["MINARI_DATASETS_PATH"] = str(trained["roots"])
    try:
        return minari.load_dataset(DATASET_ID)
    finally:
        del os.environ["MINARI_DATASETS_PATH"]


def _pool(trained) -> dict[int, dict]:
    state = load_checkpoint(str(trained["run_dir"] / "checkpoint.pt"))
    return state, {t["id"]: t for t in state["pool"]["trajectories"]}


def test_the_episodes_come_back_from_minari_as_the_run_recorded_them(trained):
    dataset = _load(trained)
    state, pool = _pool(trained)
    episodes = pd.read_parquet(trained["path"] / "episodes.parquet")
    assert dataset.total_episodes == len(episodes) >= 2
    assert dataset.observation_space.shape == (17,) and dataset.action_space.shape == (6,)
    assert (dataset.action_space.low == -1).all() and (dataset.action_space.high == 1).all()
    buffer_next = state["buffer"]["next_obs"].numpy()
    for episode_id, trajectory in zip(episodes.episode_id, episodes.trajectory, strict=True):
        e, t = dataset[int(episode_id)], pool[int(trajectory)]
        assert e.observations.shape == (201, 17) and e.actions.shape == (200, 6)
        np.testing.assert_array_equal(e.observations[:-1], t["obs"])
        np.testing.assert_array_equal(e.actions, t["actions"])
        np.testing.assert_array_equal(e.rewards, t["true_rewards"])
        np.testing.assert_array_equal(e.infos["state"][:-1], t["states"])
        # The final observation is the one the agent saw after its last step (its replay
        # buffer's next observation), restored exactly from the state kept at the episode's end.
        np.testing.assert_array_equal(e.observations[-1], buffer_next[200 * trajectory + 199])
        assert e.truncations[-1] and not e.truncations[:-1].any() and not e.terminations.any()
    assert not episodes.final_resimulated.any()


def test_each_answer_is_a_row_pointing_at_the_segments_it_judged(trained):
    dataset = _load(trained)
    labels = pd.read_parquet(trained["path"] / "labels.parquet")
    queries = pd.read_parquet(trained["path"] / "queries.parquet")
    assert len(labels) == 20 and len(queries) == 20  # two rounds of 10, one answer each
    assert set(labels.labeller_name) == {"scripted-teacher"}
    for row in labels.itertuples():
        for side in ("first", "second"):
            episode = dataset[int(getattr(row, f"{side}_episode"))]
            start = getattr(row, f"{side}_start")
            segment = episode.rewards[start:start + row.segment_length]
            assert segment.sum(dtype=np.float64) == getattr(row, f"{side}_segment_return")
    assert (dict(zip(queries.query_id, queries["aggregate"], strict=True))
            == dict(zip(labels.query_id, labels["aggregate"], strict=True)))
    info = json.loads((trained["path"] / "sepoa.json").read_text())
    assert info["task"] == "dmc:cheetah_run" and info["config"]["reward"]["hidden_dim"] == 32
    assert info["labels"] == 20 and info["labels_left_out"] == 0


def test_a_stored_segment_renders_again_as_the_labeller_saw_it(trained, tmp_path):
    dataset = _load(trained)
    labels = pd.read_parquet(trained["path"] / "labels.parquet")
    clip = sized(ClipConfig(width=64, height=64), trained["clip_size"])  # as the worker's
    env = make_env("dmc:cheetah_run", 7, 200)
    for position, side, segment in ((0, "first", 0), (3, "second", 1)):
        row = labels[(labels["round"] == 0) & (labels.position == position)].iloc[0]
        episode = dataset[int(row[f"{side}_episode"])]
        frames = iter_segment_frames(env, episode.infos["state"],
                                     int(episode.infos["context"][0]),
                                     int(row[f"{side}_start"]), int(row.segment_length), clip)
        again = encode_mp4(frames, tmp_path / f"again-{position}.mp4", clip)
        shown = trained["data"] / "clips" / "run-1" / f"r0-q{position}-{segment}.mp4"
        decoded = [_decode(path) for path in (shown, again)]
        assert decoded[0].shape == (row.segment_length, clip.height, clip.width, 3)
        np.testing.assert_array_equal(decoded[1], decoded[0])


def _decode(path) -> np.ndarray:
    with imageio.get_reader(path) as reader:
        return np.stack(list(reader.iter_data()))


def test_minari_alone_reads_it(trained):
    script = (
        "import sys, minari\n"
        f"d = minari.load_dataset({DATASET_ID!r})\n"
        "e = d[0]\n"
        "assert e.observations.shape[0] == len(e.actions) + 1 == len(e.infos['state'])\n"
        "mine = {'trainer', 'labelqueue', 'runvocab', 'server', 'sepoa'} & set(sys.modules)\n"
        "assert not mine, mine\n"
        "print(d.total_steps)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         cwd=trained["roots"], timeout=120,
                         env=os.environ | {"MINARI_DATASETS_PATH": str(trained["roots"])})
    assert out.returncode == 0, out.stderr
    assert int(out.stdout) == _load(trained).total_steps


def test_bad_input_gets_one_line_and_leaves_nothing(trained, capsys):
    roots, base = trained["roots"], trained["args"][:5]
    before = sorted(p.relative_to(roots) for p in roots.rglob("*"))
    cases = {
        "exists": (["--dataset", str(roots), "--run", "1"], "already exists"),
        "unknown run": (["--dataset", str(roots), "--run", "9"], "run 9 does not exist"),
        "no episodes": (["--dataset", str(roots), "--run", "2"], "no stored episodes"),
        "other clips folder": (
            ["--dataset", str(roots), "--run", "1", "--dataset-id", "sepoa/other-v0",
             "--clips-dir", str(roots.parent / "c")],
            "give the clips folder its worker wrote to with --clips-dir (a run trained by "
            "`sepoa experiment run` or the Slurm script: --clips-dir <results>/clips)"),
        "no run": (["--dataset", str(roots)], "--dataset needs --run"),
        "bad id": (["--dataset", str(roots), "--run", "1", "--dataset-id", "a b"],
                   "not a Minari id"),
        "non-ASCII id": (["--dataset", str(roots), "--run", "1", "--dataset-id",
                          "sepoa/\u30c7\u30fc\u30bf-v0"],
                         "use ASCII letters, digits, '-', '_' and '/' only"),
    }
    for name, (extra, message) in cases.items():
        capsys.readouterr()
        assert main(base + extra) == 2, name
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, (name, err)
    assert sorted(p.relative_to(roots) for p in roots.rglob("*")) == before
    other = roots.parent / "other"
    assert main(base + ["--dataset", str(other), "--run", "2"]) == 2
    assert not other.exists()  # not even the folders made for it


def test_a_relative_datasets_folder_works_as_the_docs_show_it(trained, tmp_path, monkeypatch,
                                                              capsys):
    monkeypatch.chdir(tmp_path)
    args = [*trained["args"][:5], "--dataset", "datasets", "--run", "1"]
    assert main(args) == 0, capsys.readouterr().err
    assert "MINARI_DATASETS_PATH=datasets" in capsys.readouterr().err
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", "datasets")
    assert minari.load_dataset(DATASET_ID).total_steps == _load(trained).total_steps
    assert not (tmp_path / "datasets" / "datasets").exists()


def test_format_hdf5_writes_minaris_hdf5_storage(trained, tmp_path, capsys, monkeypatch):
    base = trained["args"][:5]
    assert main([*base, "--dataset", str(tmp_path), "--run", "1", "--format", "hdf5"]) == 0
    assert (tmp_path / DATASET_ID / "data" / "main_data.hdf5").is_file()
    import minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    again, first = minari.load_dataset(DATASET_ID), _load(trained)
    assert again.total_steps == first.total_steps
    np.testing.assert_array_equal(again[1].infos["state"], first[1].infos["state"])
    for extra, message in (
            (["--format", "hdf5"], "--format hdf5 is a dataset's storage: it goes with "
                                   "--dataset DIR"),
            (["--dataset", str(tmp_path / "x"), "--run", "1", "--format", "csv"],
             "--format jsonl/csv/parquet and --out are for the label file")):
        capsys.readouterr()
        assert main([*base, *extra]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("task", ["dmc:cheetah_run", "metaworld:door-open", "teacher.",
                                  "my env/v2 (gym)", "x", "caf\u00e9 \u03b8"])
def test_any_runs_task_gives_a_default_dataset_id_minari_takes(task):
    """An external run's task is any text; the default id must still be one Minari takes."""
    from rundata.dataset import check_dataset_id, default_dataset_id

    dataset_id = default_dataset_id(task, 7)
    assert check_dataset_id(dataset_id) == dataset_id and dataset_id.endswith("/run-7-v0")


@pytest.mark.parametrize("damage", ["truncated", "not a zip", "an array missing"])
def test_a_damaged_episode_file_is_named_in_one_line(tmp_path, capsys, damage):
    from rundata.episodes import StoredEpisode, episode_path, episodes_dir, write_episode

    url, sessions = database(tmp_path)
    with sessions() as session:
        create_run(session, name="tiny", teacher="scripted", **RUN)
    folder = episodes_dir(tmp_path / "data" / "clips", 1)
    write_episode(folder, StoredEpisode(
        trajectory=0, observations=np.zeros((3, 2), np.float32),
        actions=np.zeros((2, 1), np.float32), rewards=np.zeros(2, np.float32),
        states=np.zeros((3, 2)), context=0, success=False))
    path = episode_path(folder, 0)
    if damage == "truncated":
        path.write_bytes(path.read_bytes()[:300])
    elif damage == "not a zip":
        path.write_bytes(b"not an npz file")
    else:
        np.savez(path, observations=np.zeros((3, 2)))
    assert main(["export", "--database-url", url, "--data-dir", str(tmp_path / "data"),
                 "--dataset", str(tmp_path / "datasets"), "--run", "1"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert f"{path} cannot be read" in err and "the file is damaged" in err
    assert not (tmp_path / "datasets").exists()

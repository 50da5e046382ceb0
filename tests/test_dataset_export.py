"""A run's data as a Minari dataset: a tiny scripted run through the worker, exported with
`sepoa export --dataset`, read back with Minari, and compared with the run's own checkpoint."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from worker_helpers import RUN, database, worker_config

from labelqueue import create_run
from sepoa.cli import main
from trainer.checkpoint import load_checkpoint
from trainer.clips import ClipConfig, render_segment
from trainer.envs import make_env
from trainer.worker import run_worker

DATASET_ID = "sepoa/dmc-cheetah_run/run-1-v0"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A finished scripted run (two rounds of 10 queries on 200-step episodes) and its export."""
    tmp = tmp_path_factory.mktemp("dataset")
    url, sessions = database(tmp)
    with sessions() as session:
        create_run(session, name="tiny", teacher="scripted", **RUN)
    data = tmp / "data"
    run_worker(worker_config(url, data))
    with sessions() as session:  # queued, never trained: no episodes
        create_run(session, name="untrained", teacher="scripted", **RUN)
    roots = tmp / "datasets"
    args = ["export", "--database-url", url, "--data-dir", str(data), "--dataset", str(roots),
            "--run", "1"]
    assert main(args) == 0
    return {"url": url, "data": data, "roots": roots, "args": args,
            "path": roots / DATASET_ID, "run_dir": data / "runs" / "run-1"}


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


def test_a_stored_segment_renders_again_as_the_run_showed_it(trained):
    dataset = _load(trained)
    _, pool = _pool(trained)
    episodes = pd.read_parquet(trained["path"] / "episodes.parquet")
    cfg = ClipConfig(width=64, height=64)
    env = make_env("dmc:cheetah_run", 7, 200)
    trajectory = int(episodes.trajectory[1])
    again = render_segment(env, dataset[1].infos["state"], int(dataset[1].infos["context"][0]),
                           30, 5, cfg)
    original = render_segment(env, pool[trajectory]["states"], 0, 30, 5, cfg)
    np.testing.assert_array_equal(again, original)
    assert again.std() > 0


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
        "no run": (["--dataset", str(roots)], "--dataset needs --run"),
        "bad id": (["--dataset", str(roots), "--run", "1", "--dataset-id", "a b"],
                   "not a Minari id"),
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

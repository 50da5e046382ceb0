"""`sepoa label-dataset`: a labelling-only run over a dataset export is queued with its rounds,
and a dataset no worker could serve is refused in one line, with nothing stored."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from labelling_helpers import drop_states, edit_info, exported_dataset, malformed_copies
from sqlalchemy import select

from labelqueue import Run, make_engine, session_factory
from sepoa.cli import main


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return exported_dataset(tmp_path_factory.mktemp("cli") / "datasets")


def _runs(data) -> list[Run]:
    if not (data / "queue.db").exists():
        return []
    engine = make_engine(f"sqlite:///{data / 'queue.db'}")
    try:
        with session_factory(engine)() as session:
            runs = list(session.scalars(select(Run)))
            session.expunge_all()
            return runs
    finally:
        engine.dispose()


def test_a_labelling_run_is_queued_over_the_dataset(source, tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["label-dataset", str(source), "--data-dir", str(data), "--budget", "30",
                 "--per-round", "5", "--selection", "uniform", "--preset", "tiny",
                 "--clip-size", "128x128", "--set", "reward.hidden_dim=16"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("run 1 ") and "30 answers" in out and "4 episodes" in out
    [run] = _runs(data)
    assert (run.status, run.task, run.algo, run.budget, run.teacher, run.clip_size) == (
        "queued", "dmc:cheetah_run", "pebble", 30, "human", "128x128")
    assert run.dataset == str(source.resolve())
    assert run.name == "label sepoa/dmc-cheetah_run/source-v0"
    assert run.config == {
        "reward.hidden_dim": 16, "feedback.selection": "uniform",
        "feedback.first_round_selection": "uniform", "feedback.wait_for_labels": True,
        "feedback.segment_length": 20,  # the tiny preset's
        "feedback.per_round": 5}


def test_the_segment_defaults_to_the_shortest_episode_when_the_presets_is_longer(
        source, tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["label-dataset", str(source), "--data-dir", str(data), "--budget", "5"]) == 0
    [run] = _runs(data)
    assert run.config["feedback.segment_length"] == 50  # the small preset's fits in 60 steps
    capsys.readouterr()
    longer = exported_dataset(tmp_path / "short", length=30)
    assert main(["label-dataset", str(longer), "--data-dir", str(data), "--budget", "5"]) == 0
    assert _runs(data)[1].config["feedback.segment_length"] == 30


def _copy(source, tmp_path, name):
    path = tmp_path / name
    shutil.copytree(source, path)
    return path


def test_a_dataset_no_worker_could_serve_is_refused_in_one_line_and_nothing_is_stored(
        source, tmp_path, capsys):
    unknown = _copy(source, tmp_path, "unknown")
    edit_info(unknown, task="dmc:cheetah_fly")
    spaces = _copy(source, tmp_path, "spaces")
    edit_info(spaces, obs_dim=5)
    walker = _copy(source, tmp_path, "walker")
    edit_info(walker, task="dmc:walker_walk")
    stateless = _copy(source, tmp_path, "stateless")
    drop_states(stateless)
    cases = {
        "missing": ([str(tmp_path / "nowhere")], "no dataset at"),
        "unknown task": ([str(unknown)], "task 'dmc:cheetah_fly' is not one this project knows"),
        "spaces": ([str(spaces)], "do not match sepoa.json (obs_dim 5"),
        "another task's episodes": (
            [str(walker)], "observations of 17, actions of 6 and physics states of 18 values; "
            "dmc:walker_walk has 24, 6 and 18"),
        "no states": ([str(stateless)], "has no physics states"),
        "segment": ([str(source), "--segment-length", "61"],
                    "segment length 61: give 1 to 60"),
        "config": ([str(source), "--set", "reward.widht=3"], "reward.widht"),
        "selection": ([str(source), "--selection", "entropy"], "invalid choice: 'entropy'"),
        "budget": ([str(source), "--budget", "0"], "'0' is not a budget"),
        "blank name": ([str(source), "--name", " \t"], "name ' \\t' is blank"),
    }
    data = tmp_path / "data"
    for name, (extra, message) in cases.items():
        capsys.readouterr()
        args = ["label-dataset", "--data-dir", str(data), "--budget", "10", *extra]
        try:
            status = main(args)
        except SystemExit as exit:  # refused by the argument parser
            status = exit.code
        assert status == 2, name
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, (name, err)
        assert not (data / "queue.db").exists(), name


def test_a_scripted_run_says_who_answers(source, tmp_path, capsys):
    assert main(["label-dataset", str(source), "--data-dir", str(tmp_path / "data"),
                 "--budget", "5", "--teacher", "scripted"]) == 0
    out = capsys.readouterr().out
    assert "the scripted teacher answers from the dataset's true rewards" in out
    assert "people label it" not in out


def test_malformed_datasets_get_one_line_from_label_dataset_and_reward_fit(
        source, tmp_path, capsys):
    data = tmp_path / "data"
    for name, (path, message) in malformed_copies(source, tmp_path / "bad").items():
        for args in (["label-dataset", str(path), "--data-dir", str(data), "--budget", "10"],
                     ["reward", "fit", str(path), "--out", str(tmp_path / "r.pt")]):
            capsys.readouterr()
            assert main(args) == 2, (name, args[0])
            err = capsys.readouterr().err
            assert message in err and len(err.strip().splitlines()) == 1, (name, args[0], err)
    assert not data.exists() and not (tmp_path / "r.pt").exists()


def test_the_dataset_is_checked_with_mujoco_rendering_through_egl(source, tmp_path):
    """As the trainer's commands, label-dataset sets MUJOCO_GL=egl before MuJoCo is imported
    (the README's default; MuJoCo reads it once, on import)."""
    root = Path(__file__).resolve().parents[1]
    code = ("import os, sys; from sepoa.cli import main; status = main(sys.argv[1:]); "
            "print(status, 'mujoco' in sys.modules, os.environ.get('MUJOCO_GL'))")
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"} | {
        "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(
        [sys.executable, "-c", code, "label-dataset", str(source), "--budget", "5",
         "--data-dir", str(tmp_path / "data")], env=env, capture_output=True, text=True,
        timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[-1] == "0 True egl", done.stdout

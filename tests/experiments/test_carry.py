"""`sepoa experiment pack`: a grid stopped on one machine goes on on another from its checkpoints,
its finished runs counted as finished; packing under a live worker is refused."""

from __future__ import annotations

import contextlib
import csv
import json
import signal
import sqlite3
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
from database_helpers import BACKENDS, postgres_schema
from worker_helpers import wait_for, worker_config

from labelqueue import release_run
from sepoa.cli import main
from trainer.worker import run_worker

ROOT = Path(__file__).resolve().parents[2]

SPEC = """
name = "tiny"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]

[overrides]
eval_every = 200
"feedback.per_round" = 10

[variants.PEBBLE]
algo = "pebble"
"""


def test_a_packed_grid_resumes_on_another_machine_from_its_checkpoints(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    here, there = tmp_path / "here", tmp_path / "there"
    runs = "tiny/dmc-cheetah_run/PEBBLE/eps0.3"
    # Seed 1 finishes here; seed 0 is stopped after its first checkpoint.
    assert main(["experiment", "run", str(spec), "--results", str(here), "--no-workers",
                 "--seed", "1"]) == 0
    run_worker(worker_config(f"sqlite:///{here / 'queue.db'}", tmp_path / "data",
                             results_dir=here, threads=1))
    launcher = subprocess.Popen(
        [sys.executable, "-m", "sepoa.cli", "experiment", "run", str(spec), "--results",
         str(here), "--workers", "1", "--threads", "1"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for(lambda: (here / runs / "s0" / "checkpoint.pt").exists()
             or launcher.poll() is not None, timeout=90, what="seed 0's first checkpoint")
    capsys.readouterr()
    archive = tmp_path / "carry" / "tiny.tar.gz"
    # A worker still trains seed 0: its checkpoint would be behind the run.
    assert main(["experiment", "pack", str(spec), "--results", str(here),
                 "--out", str(archive)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "held by live workers" in err
    assert f"{runs}/s0 (running, worker " in err and "Stop their launcher" in err
    assert not archive.exists()

    launcher.send_signal(signal.SIGTERM)
    out, _ = launcher.communicate(timeout=60)
    assert "stopping 1 worker(s)" in out
    assert not (here / runs / "s0" / "done.json").exists()
    assert main(["experiment", "pack", str(spec), "--results", str(here),
                 "--out", str(archive)]) == 0
    out = capsys.readouterr().out
    assert "1 unfinished run(s) with their checkpoints, 1 finished" in out
    assert "the queue database" in out
    with tarfile.open(archive) as tar:
        names = set(tar.getnames())
        tar.extractall(there, filter="data")
    assert {f"{runs}/s0/checkpoint.pt", f"{runs}/s1/done.json", "queue.db",
            "tiny/spec.toml", "tiny/sessions.csv"} <= names
    assert f"{runs}/s1/checkpoint.pt" not in names
    assert not any("/tb/" in name for name in names)
    with sqlite3.connect(there / "queue.db") as db:
        statuses = dict(db.execute("SELECT grid_key, status FROM runs").fetchall())
    assert statuses == {f"{runs}/s0": "queued", f"{runs}/s1": "finished"}  # s0 released

    finished_here = (here / runs / "s1" / "done.json").read_text()
    assert main(["experiment", "run", str(spec), "--results", str(there),
                 "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "0 enqueued" in out and "tiny: 2 finished" in out
    assert json.loads((there / runs / "s0" / "done.json").read_text())["step"] == 600
    assert (there / runs / "s1" / "done.json").read_text() == finished_here
    # The launcher here and the one there: two periods of the grid's training, both ended.
    with (there / "tiny" / "sessions.csv").open() as f:
        assert [row["ended_by"] for row in csv.DictReader(f)] == ["signal 15", "finished"]
    log = (there / "workers.log").read_text()
    assert "resuming dmc:cheetah_run pebble" in log and "starting" not in log
    steps = [int(line.split(",")[0]) for line in
             (there / runs / "s0" / "episodes.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 600


def test_bad_input_to_pack_gets_one_line(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    out = str(tmp_path / "a.tar.gz")
    results = tmp_path / "results"
    assert main(["experiment", "pack", str(spec), "--results", str(results), "--out", out]) == 2
    assert "no such folder" in capsys.readouterr().err
    results.mkdir()
    (results / "queue.db").write_text("not a database")
    assert main(["experiment", "pack", str(spec), "--results", str(results), "--out", out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "queue database" in err and "not a database" in err
    assert list(tmp_path.glob("*a.tar.gz*")) == []  # no archive, and no partial one


def test_pack_carries_the_episode_stores_and_the_stop_rules_record(tmp_path: Path) -> None:
    from experiments.carry import pack
    from experiments.launch import run_experiment
    from experiments.queue import grid_key, spec_rows
    from experiments.spec import load_spec
    from labelqueue import claim_run, make_engine, session_factory
    from rundata.episodes import episodes_dir

    results = tmp_path / "results"
    specs = {}
    for name in ("axb", "a_b"):  # `_` is one character, not any
        path = tmp_path / f"{name}.toml"
        path.write_text(SPEC.replace('name = "tiny"', f'name = "{name}"'))
        specs[name] = load_spec(path)
        assert run_experiment(specs[name], results=results, workers=0,
                              echo=lambda line: None) == 0
        if name == "axb":  # a live worker trains a run of the other grid
            engine = make_engine(f"sqlite:///{results / 'queue.db'}")
            with session_factory(engine)() as session:
                assert claim_run(session, worker_id="w") is not None
            engine.dispose()
    spec = specs["a_b"]
    engine = make_engine(f"sqlite:///{results / 'queue.db'}")
    rows = spec_rows(spec, session_factory(engine))
    engine.dispose()
    run = spec.runs()[0]
    key = grid_key(spec, run)
    (results / key).mkdir(parents=True)
    (results / key / "checkpoint.pt").write_bytes(b"weights")
    episodes = episodes_dir(results / "clips", rows[key].id)
    episodes.mkdir(parents=True)
    for name in ("episode-0.npz", "end-0.npz", ".end-1.npz.7.tmp"):
        (episodes / name).write_bytes(b"npz")
    (results / "a_b" / "stop_rule.json").write_text('{"hours": 2, "seeds_not_started": [1]}')
    out = tmp_path / "a_b.tar.gz"
    (tmp_path / "a_b.tar.gz.partial").write_bytes(b"another pack's")

    packed = pack(spec, results, out)
    with tarfile.open(out) as tar:
        names = set(tar.getnames())
    store = f"clips/run-{rows[key].id}/episodes"
    assert {f"{key}/checkpoint.pt", f"{store}/episode-0.npz", f"{store}/end-0.npz",
            "a_b/stop_rule.json", "a_b/spec.toml", "queue.db"} <= names
    assert f"{store}/.end-1.npz.7.tmp" not in names
    assert packed.episode_stores == 1
    assert (tmp_path / "a_b.tar.gz.partial").read_bytes() == b"another pack's"


def _grid_with_a_stored_run(url: str, results: Path, spec_path: Path) -> tuple[str, Path]:
    """The tiny grid enqueued in the queue at `url`, seed 0 stopped after its first checkpoint
    with one stored episode; its grid key and episode store."""
    from experiments.launch import run_experiment
    from experiments.queue import grid_key, spec_rows
    from experiments.spec import load_spec
    from labelqueue import make_engine, session_factory
    from rundata.episodes import episodes_dir

    spec_path.write_text(SPEC)
    spec = load_spec(spec_path)
    assert run_experiment(spec, results=results, database_url=url, workers=0,
                          echo=lambda line: None) == 0
    engine = make_engine(url)
    rows = spec_rows(spec, session_factory(engine))
    engine.dispose()
    key = grid_key(spec, spec.runs()[0])
    (results / key).mkdir(parents=True)
    (results / key / "checkpoint.pt").write_bytes(b"weights")
    store = episodes_dir(results / "clips", rows[key].id)
    store.mkdir(parents=True)
    (store / "episode-0.npz").write_bytes(b"npz")
    return key, store


@pytest.mark.parametrize("backend", BACKENDS)
def test_pack_finds_the_episode_stores_by_the_queue_it_is_given(
        backend: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from labelqueue import claim_run, make_engine, session_factory

    with contextlib.ExitStack() as stack:
        url = (f"sqlite:///{tmp_path / 'elsewhere' / 'queue.db'}" if backend == "sqlite"
               else stack.enter_context(postgres_schema()))
        results, spec = tmp_path / "results", tmp_path / "spec.toml"
        key, store = _grid_with_a_stored_run(url, results, spec)
        archive = tmp_path / "tiny.tar.gz"
        pack = ["experiment", "pack", str(spec), "--results", str(results), "--out",
                str(archive), "--database-url", url]
        engine = make_engine(url)
        with session_factory(engine)() as session:
            held = claim_run(session, worker_id="w")
            assert held is not None
        engine.dispose()
        assert main(pack) == 2  # a live worker holds a run: its checkpoint would be behind
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "held by live workers" in err
        assert "(running, worker w, heartbeat" in err and not archive.exists()

        engine = make_engine(url)
        with session_factory(engine)() as session:
            release_run(session, run_id=held.id, worker_id="w")
        engine.dispose()
        capsys.readouterr()
        assert main(pack) == 0
        out = capsys.readouterr().out
        with tarfile.open(archive) as tar:
            names = set(tar.getnames())
    assert {f"{key}/checkpoint.pt", f"{store.relative_to(results)}/episode-0.npz"} <= names
    assert "1 episode store(s)" in out
    if backend == "sqlite":  # there, the launcher's default queue: <results>/queue.db
        assert "queue.db" in names and "the queue database;" in out
    else:  # the queue stays on its server, the runs' ids with it
        assert "queue.db" not in names
        assert "not the queue, which stays at postgresql" in out and "--database-url" in out


def test_pack_without_a_queue_says_which_one_it_needs(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A grid whose queue is elsewhere (PostgreSQL) has its episode stores under the queue's run
    ids: packed without that queue, the archive would leave them behind."""
    results, spec = tmp_path / "results", tmp_path / "spec.toml"
    _grid_with_a_stored_run(f"sqlite:///{tmp_path / 'elsewhere' / 'queue.db'}", results, spec)
    archive = tmp_path / "tiny.tar.gz"
    assert main(["experiment", "pack", str(spec), "--results", str(results),
                 "--out", str(archive)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"no queue database at {results / 'queue.db'}" in err and "--database-url" in err
    assert not archive.exists()


def test_pack_and_keep_refuse_an_out_path_in_the_way_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """An --out that is a folder (pack) or lies under a file: pack said
    `.archives.<hex>.partial: Is a directory` or `notes.txt: File exists`, keep the latter."""
    spec = tmp_path / "spec.toml"
    spec.write_text(SPEC)
    results = tmp_path / "results"
    assert main(["experiment", "run", str(spec), "--results", str(results), "--no-workers"]) == 0
    notes, folder = tmp_path / "notes.txt", tmp_path / "archives"
    notes.write_text("kept\n")
    folder.mkdir()
    capsys.readouterr()
    for action, out, words in (
            ("pack", folder, f"--out {folder} is a folder; give the archive's file name"),
            ("pack", notes / "grid.tar.gz", f"{notes} is a file, not a folder"),
            ("keep", notes, f"{notes} is a file, not a folder"),
            ("keep", notes / "kept", f"{notes} is a file, not a folder")):
        assert main(["experiment", action, str(spec), "--results", str(results),
                     "--out", str(out)]) == 2, (action, out)
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], (action, out, lines)
    assert notes.read_text() == "kept\n" and list(folder.iterdir()) == []
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".partial")] == []

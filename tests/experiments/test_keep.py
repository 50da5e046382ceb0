"""`sepoa experiment keep`: a grid's finished runs, without checkpoints, in a folder to commit
beside its report; `sepoa report` reads it, and copied back into a results folder the launcher
counts those runs as finished."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import pytest

from experiments.launch import default_database, run_experiment
from experiments.queue import grid_key, spec_rows
from experiments.sessions import FILE as SESSIONS
from experiments.spec import load_spec
from labelqueue import claim_run, finish_run, make_engine, session_factory, set_run_status
from runvocab.config import to_dict
from sepoa.cli import main

SPEC = """
name = "kept"
preset = "tiny"
steps = 1000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]

[variants.A]
algo = "pebble"
"""


def test_finished_runs_are_kept_without_checkpoints_and_adopted_where_copied_back(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    grid = results / "kept"
    (grid / SESSIONS).write_text("started_at,ended_at,workers,threads,ended_by,alive_at\n"
                                 "2026-11-28T08:00:00+00:00,2026-11-28T09:00:00+00:00,2,1,"
                                 "signal 15,2026-11-28T09:00:00+00:00\n")
    finished, unfinished = spec.runs()
    for run, done in ((finished, True), (unfinished, False)):
        folder = grid / run.dir
        (folder / "tb").mkdir(parents=True)
        (folder / "tb" / "events.out.tfevents").write_bytes(b"tb")
        (folder / "checkpoint.pt").write_bytes(b"weights" * 1000)
        (folder / "config.json").write_text(json.dumps(to_dict(run.config()), default=str))
        (folder / "eval.csv").write_text("step,return,return_std,success_rate,labels_used\n"
                                         "1000,12.5,0.0,0.0,30\n")
        (folder / "episodes.csv").write_text("step,episode,return\n1000,0,10.0\n")
        (folder / "labels.jsonl").write_text('{"answer": "first"}\n' * 30)
        if done:
            (folder / "done.json").write_text(json.dumps({"step": 1000, "labels_used": 30}))

    out = tmp_path / "report" / "runs"
    assert main(["experiment", "keep", str(spec_path), "--results", str(results),
                 "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"{out}: 1 finished run(s) of kept and its grid files" in said
    assert "1 run(s) not finished left out" in said and "still running" not in said
    kept = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert kept == sorted(["spec.toml", SESSIONS] + [f"{finished.dir}/{name}" for name in (
        "config.json", "done.json", "episodes.csv", "eval.csv", "labels.jsonl.gz")])
    assert gzip.decompress((out / finished.dir / "labels.jsonl.gz").read_bytes()) == \
        (grid / finished.dir / "labels.jsonl").read_bytes()
    assert main(["report", str(out)]) == 0  # a results folder of the grid in itself

    # Another machine: copied into a fresh results folder, the finished run is adopted.
    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(out, elsewhere / "kept")
    assert run_experiment(spec, results=elsewhere, workers=0, echo=lambda line: None) == 0
    engine = make_engine(default_database(elsewhere))
    rows = spec_rows(spec, session_factory(engine))
    engine.dispose()
    assert [str(rows[grid_key(spec, run)].status) for run in (finished, unfinished)] == [
        "finished", "queued"]


def test_keep_of_a_grid_never_run_is_one_line(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    assert main(["experiment", "keep", str(spec_path), "--results", str(tmp_path / "none"),
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no grid (no spec.toml)" in err[0]


@pytest.mark.parametrize("status", ["stopped", "failed"])
def test_finished_results_copied_over_a_stopped_or_failed_run_are_adopted(
        tmp_path: Path, status: str) -> None:
    """A worker would start such a run afresh, deleting a folder without a checkpoint."""
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    engine = make_engine(default_database(results))
    sessions = session_factory(engine)
    run = spec.runs()[0]
    with sessions() as session:
        row = spec_rows(spec, sessions)[grid_key(spec, run)]
        if status == "failed":
            claim_run(session, worker_id="w")
            finish_run(session, run_id=row.id, worker_id="w", status="failed", error="boom")
        else:
            set_run_status(session, run_id=row.id, status="stopped")
    folder = results / grid_key(spec, run)  # trained to the end elsewhere, copied in
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(to_dict(run.config()), default=str))
    (folder / "done.json").write_text(json.dumps({"step": 1000, "labels_used": 30}))
    said: list[str] = []
    assert run_experiment(spec, results=results, workers=0, echo=said.append) == 0
    row = spec_rows(spec, sessions)[grid_key(spec, run)]
    engine.dispose()
    assert (str(row.status), row.step, row.error) == ("finished", 1000, None)
    assert "0 queued again" in said[0] and "1 finished before" in said[0]

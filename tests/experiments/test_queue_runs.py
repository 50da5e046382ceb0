"""Experiments as queue runs: a spec's grid enqueued once per grid key, trained by workers into
`<results>/<spec>/<run>/`; a changed grid refused without --force; two launchers never train a
run twice; a failing run is reported while the others finish; a killed launch resumes; the
one-command launch with local workers. The Slurm script: test_slurm.py, test_slurm_cluster.py."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import func, select
from worker_helpers import wait_for, worker_config

from experiments.launch import run_experiment
from experiments.queue import enqueue_spec, grid_key, spec_rows
from experiments.spec import Spec, SpecError, load_spec
from labelqueue import (
    Run,
    RunStatus,
    claim_run,
    finish_run,
    grid_runs,
    make_engine,
    migrate,
    release_run,
    schema_revisions,
    session_factory,
)
from sepoa.cli import main
from trainer.worker import run_worker

ROOT = Path(__file__).resolve().parents[2]

TINY = """
name = "tiny"
preset = "tiny"
steps = {steps}
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = {seeds}

[overrides]
eval_every = 200
"skill.pretrain_steps" = 200
"feedback.per_round" = 10
"""


def write(folder: Path, text: str, name: str = "spec.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def quiet(line: str) -> None:
    pass


def sessions_for(results: Path):  # noqa: ANN201
    url = f"sqlite:///{results / 'queue.db'}"
    migrate(url)
    return url, session_factory(make_engine(url))


def grid_spec(tmp_path: Path, seeds: str = "[0, 1]", steps: int = 400) -> Spec:
    return load_spec(write(tmp_path, TINY.format(steps=steps, seeds=seeds) + """
[variants.PEBBLE]
algo = "pebble"
[variants.S-EPOA]
algo = "sepoa"
"""), check=False)


def test_enqueueing_a_spec_twice_adds_each_run_once(tmp_path: Path) -> None:
    spec, results = grid_spec(tmp_path), tmp_path / "results"
    lines: list[str] = []
    assert run_experiment(spec, results=results, workers=0, dry_run=True,
                          echo=lines.append) == 0
    assert "4 enqueued" in lines[0] and "dry run, nothing written" in lines[0]
    assert not results.exists()
    assert run_experiment(spec, results=results, workers=0, echo=lines.append) == 0
    assert "4 enqueued" in lines[-2] and "sepoa worker --database-url" in lines[-1]
    assert run_experiment(spec, results=results, workers=0, echo=lines.append) == 0
    assert "0 enqueued" in lines[-2] and "0 finished, 4 queued or running" in lines[-2]
    assert run_experiment(spec, results=results, workers=0, dry_run=True,
                          echo=lines.append) == 0
    assert "0 enqueued" in lines[-1] and "dry run, nothing written" in lines[-1]
    assert (results / "tiny" / "spec.toml").read_text() == spec.source
    _, sessions = sessions_for(results)
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
        assert session.scalar(select(func.count()).select_from(Run)) == 4
    assert sorted(rows) == sorted(grid_key(spec, run) for run in spec.runs())
    row = rows["tiny/dmc-cheetah_run/S-EPOA/eps0.3/s1"]
    assert (row.algo, row.seed, row.teacher, row.teacher_params) == ("sepoa", 1, "scripted",
                                                                     {"eps": 0.3})
    assert row.config == {"steps": 400, "eval_every": 200, "skill.pretrain_steps": 200,
                          "feedback.per_round": 10}
    # A grown grid adds only its new runs.
    bigger = grid_spec(tmp_path, seeds="[0, 1, 2]")
    assert run_experiment(bigger, results=results, workers=0, echo=lines.append) == 0
    assert "2 enqueued" in lines[-2]


def _finish_all(sessions, worker: str = "w") -> list[int]:  # noqa: ANN001
    ids = []
    with sessions() as session:
        while (run := claim_run(session, worker_id=worker)) is not None:
            finish_run(session, run_id=run.id, worker_id=worker)
            ids.append(run.id)
    return ids


def test_a_changed_grid_is_refused_unless_forced(tmp_path: Path) -> None:
    spec, results = grid_spec(tmp_path, seeds="[0]"), tmp_path / "results"
    run_experiment(spec, results=results, workers=0, echo=quiet)
    _, sessions = sessions_for(results)
    old = _finish_all(sessions)
    folder = results / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s0"
    folder.mkdir(parents=True)
    (folder / "done.json").write_text("{}")
    changed = load_spec(write(tmp_path, spec.source.replace("eval_every = 200",
                                                            "eval_every = 100"), "changed.toml"))
    with pytest.raises(SpecError) as err:
        run_experiment(changed, results=results, workers=0, echo=quiet)
    message = str(err.value)
    assert "2 run(s) of spec 'tiny' with another definition" in message
    assert "tiny/dmc-cheetah_run/PEBBLE/eps0.3/s0: run 1, finished: config" in message
    assert "--force" in message
    assert (folder / "done.json").exists()
    # More steps redefine finished runs too.
    longer = load_spec(write(tmp_path, spec.source.replace("steps = 400", "steps = 800"),
                             "longer.toml"))
    with pytest.raises(SpecError, match="with another definition"):
        run_experiment(longer, results=results, workers=0, echo=quiet)

    lines: list[str] = []
    assert run_experiment(changed, results=results, workers=0, force=True,
                          echo=lines.append) == 0
    assert "2 redefined" in lines[0]
    assert not folder.exists()
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
        kept = [session.get(Run, run_id) for run_id in old]
    assert all(row.status is RunStatus.QUEUED and row.id not in old for row in rows.values())
    assert all(row.grid_key is None and row.status is RunStatus.FINISHED for row in kept)
    assert all(row.config["eval_every"] == 100 for row in rows.values())

    # A redefined run a worker is training is not taken from it, nor is any other redefined
    # run let go, whichever comes first.
    with sessions() as session:  # the second of the two redefined runs is held
        first = claim_run(session, worker_id="other")
        assert claim_run(session, worker_id="busy") is not None and first is not None
        release_run(session, run_id=first.id, worker_id="other", untouched=True)
    rows_before = {key: (row.id, row.status) for key, row in spec_rows(changed, sessions).items()}
    for key in rows_before:
        (results / key).mkdir(parents=True, exist_ok=True)
    with pytest.raises(SpecError, match="is running on worker 'busy'") as err:
        run_experiment(spec, results=results, workers=0, force=True, echo=quiet)
    assert {key: (row.id, row.status) for key, row in spec_rows(changed, sessions).items()} \
        == rows_before
    assert all((results / key).is_dir() for key in rows_before)
    assert str(err.value).startswith("cannot redefine 1 run(s) a worker holds (nothing was "
                                     "changed): tiny/dmc-cheetah_run/S-EPOA/eps0.3/s0: run ")
    assert str(err.value).endswith("is running on worker 'busy'; stop them first")


def test_two_launchers_on_one_spec_enqueue_and_train_each_run_once(tmp_path: Path) -> None:
    spec, results = grid_spec(tmp_path, seeds="[0, 1, 2, 3, 4]"), tmp_path / "results"
    results.mkdir()
    _, sessions = sessions_for(results)
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def launcher() -> None:
        start.wait()
        try:
            enqueue_spec(spec, sessions, results)
        except BaseException as err:  # noqa: BLE001
            errors.append(err)

    claimed: dict[str, list[int]] = {}

    def worker(name: str) -> None:
        start.wait()
        claimed[name] = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            got = _finish_all(sessions, name)
            claimed[name] += got
            if got == [] and len(sum(claimed.values(), [])) == 10:
                return
            time.sleep(0.01)

    threads = [threading.Thread(target=launcher), threading.Thread(target=launcher),
               threading.Thread(target=worker, args=("a",)),
               threading.Thread(target=worker, args=("b",))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors
    with sessions() as session:
        assert session.scalar(select(func.count()).select_from(Run)) == 10
    trained = claimed["a"] + claimed["b"]
    assert sorted(trained) == list(range(1, 11))  # every run once, none twice


@pytest.mark.slow
def test_a_worker_trains_the_grid_into_the_results_folder_and_reports_a_failure(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "not-a-snapshot.pt"
    broken.write_text("not a snapshot")
    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0, 1]") + f"""
[variants.S-EPOA]
algo = "sepoa"
[variants.broken]
algo = "sepoa"
"skill.snapshot" = "{broken}"
""")
    results = tmp_path / "results"
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--no-workers"]) == 0
    url, sessions = sessions_for(results)
    run_worker(worker_config(url, tmp_path / "data", results_dir=results, threads=1))

    root = results / "tiny" / "dmc-cheetah_run"
    for seed in (0, 1):
        folder = root / "S-EPOA" / "eps0.3" / f"s{seed}"
        assert json.loads((folder / "done.json").read_text())["step"] == 400
        assert (folder / "eval.csv").read_text().splitlines()[-1].startswith("400,")
        config = json.loads((folder / "config.json").read_text())
        assert config["skill"]["snapshot_dir"] == str(results / "snapshots")
    # Each seed pretrained its own snapshot, once, under the results folder.
    snapshots = sorted(p.name for p in (results / "snapshots").glob("*.pt"))
    assert [name.split("-")[4] for name in snapshots] == ["s0", "s1"]
    assert "is not a readable skill snapshot" in json.loads(
        (root / "broken" / "eps0.3" / "s0" / "failed.json").read_text())["reason"]
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
    assert sorted(str(r.status) for r in rows.values()) == ["failed"] * 2 + ["finished"] * 2
    assert not list((tmp_path / "data").glob("runs/*"))  # nothing outside the results folder

    capsys.readouterr()
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    table = capsys.readouterr().out
    assert "tiny: 4 runs: 2 failed, 2 finished" in table
    assert "S-EPOA   0.3  -       1     finished  400/400" in table
    assert "tiny/dmc-cheetah_run/broken/eps0.3/s1: ValueError" in table
    assert main(["report", str(results / "tiny")]) == 0
    report = (results / "tiny" / "report" / "final.md").read_text()
    assert "S-EPOA" in report and "2/2" in report

    # Run again: the finished runs stay, the failed ones are queued again.
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--no-workers"]) == 0
    assert "0 enqueued, 2 queued again" in capsys.readouterr().out
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
    assert sorted(str(r.status) for r in rows.values()) == ["finished"] * 2 + ["queued"] * 2

    # The results folder carried to a new queue database (another machine): the finished runs
    # are recorded as finished, not trained again; the failed ones are queued; a finished
    # folder whose config is not the spec's run is not taken for it.
    (results / "queue.db").unlink()
    tampered = root / "S-EPOA" / "eps0.3" / "s1" / "config.json"
    config = json.loads(tampered.read_text())
    tampered.write_text(json.dumps(config | {"steps": 500}))
    capsys.readouterr()
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--no-workers"]) == 0
    assert "1 finished before (their folders' results kept)" in capsys.readouterr().out
    url, sessions = sessions_for(results)
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
    status = {key.split("/", 2)[2]: str(row.status) for key, row in rows.items()}
    assert status == {"S-EPOA/eps0.3/s0": "finished", "S-EPOA/eps0.3/s1": "queued",
                      "broken/eps0.3/s0": "queued", "broken/eps0.3/s1": "queued"}
    assert rows["tiny/dmc-cheetah_run/S-EPOA/eps0.3/s0"].step == 400


@pytest.mark.slow
def test_one_command_trains_with_local_workers_and_a_killed_launch_resumes(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = write(tmp_path, TINY.format(steps=600, seeds="[0]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    results = tmp_path / "results"
    folder = results / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s0"
    launcher = subprocess.Popen(
        [sys.executable, "-m", "sepoa.cli", "experiment", "run", str(spec_path), "--results",
         str(results), "--workers", "1", "--threads", "1"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    wait_for(lambda: (folder / "checkpoint.pt").exists() or launcher.poll() is not None,
             timeout=90, what="the first checkpoint")
    launcher.send_signal(signal.SIGTERM)
    out, _ = launcher.communicate(timeout=60)
    assert launcher.returncode == 128 + signal.SIGTERM, out
    assert "worker " in out and "-exp-0 started" in out and "stopping 1 worker(s)" in out
    assert not (folder / "done.json").exists()

    capsys.readouterr()
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--threads", "1"]) == 0
    out = capsys.readouterr().out
    assert "0 enqueued" in out and "tiny: 1 finished" in out
    assert json.loads((folder / "done.json").read_text())["step"] == 600
    steps = [int(line.split(",")[0]) for line in
             (folder / "episodes.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 600
    log = (results / "workers.log").read_text()
    assert "resuming dmc:cheetah_run pebble" in log  # from the killed launch's checkpoint


def test_the_device_given_to_experiment_run_is_the_one_its_workers_train_on(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = write(tmp_path, TINY.format(steps=200, seeds="[0]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    results = tmp_path / "results"
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--threads", "1", "--device", "cpu"]) == 0
    folder = results / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s0"
    assert json.loads((folder / "config.json").read_text())["device"] == "cpu"
    assert "tiny: 1 finished" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [
    (["experiment", "run", "missing.toml"], "error: missing.toml: cannot read the spec"),
    (["experiment", "run", "{spec}", "--device", "gpu"],
     "error: unknown device 'gpu'; valid: auto, cpu, cuda, cuda:<index>"),
    (["experiment", "run", "{spec}", "--no-workers", "--device", "cpu"],
     "error: --device is for local workers"),
    (["experiment", "run", "{spec}", "--workers", "0"], "error: --workers must be at least 1"),
    (["experiment", "run", "{spec}", "--database-url", "mysql://x/y"], "error: "),
    (["experiment", "status", "{spec}", "--results", "{tmp}/nothing"],
     "error: no queue database at"),
    (["experiment", "slurm", "{spec}", "--workers", "0", "--database-url",
      "postgresql+psycopg://h/d"],
     "error: --workers and --threads must be at least 1"),
    # psycopg2's URL form, where this project installs psycopg (3): refused at the door.
    (["experiment", "run", "{spec}", "--no-workers", "--dry-run", "--database-url",
      "postgresql://u:pw@h/d"], "error: 'postgresql://u:***@h/d' needs the psycopg2 driver, "
                                "which is not installed; use sqlite:///PATH or "
                                "postgresql+psycopg://"),
    (["experiment", "status", "{spec}", "--database-url", "postgresql://h/d"],
     "error: 'postgresql://h/d' needs the psycopg2 driver"),
    (["experiment", "slurm", "{spec}", "--workers", "1", "--database-url", "postgresql://h/d"],
     "error: 'postgresql://h/d' needs the psycopg2 driver"),
])
def test_bad_input_gets_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                 argv: list[str], message: str) -> None:
    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    argv = [a.format(spec=spec_path, tmp=tmp_path) for a in argv]
    assert main(argv + ["--results", str(tmp_path / "r")] if "--results" not in argv
                and argv[1] == "run" else argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1, err
    assert not (tmp_path / "r" / "queue.db").exists()  # refused before anything was stored


def test_status_of_a_sqlite_database_on_an_older_schema_reads_a_migrated_copy(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A grid's database made by an older sepoa (its workers still running that one): status
    reads a migrated copy and says so, leaving the database at its own revision."""
    from alembic import command

    from labelqueue.schema import alembic_config

    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    results = tmp_path / "results"
    results.mkdir()
    (results / "queue.db").touch()
    argv = ["experiment", "status", str(spec_path), "--results", str(results)]
    assert main(argv) == 2
    assert "has no schema yet: nothing enqueued" in capsys.readouterr().err
    url = f"sqlite:///{results / 'queue.db'}"
    command.upgrade(alembic_config(url), "0010")
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "tiny: 1 runs: 1 not queued" in out
    assert "(read from a migrated copy: the database's schema is at revision 0010" in out
    assert schema_revisions(url)[0] == "0010"  # left as it was
    # Migrated by this version's launcher, it is read as it is.
    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--no-workers"]) == 0
    capsys.readouterr()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "tiny: 1 runs: 1 queued" in out and "migrated copy" not in out


def test_part_of_a_grid_trained_on_another_host_counts_as_finished_in_the_whole(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--variant`/`--seed` train part of a grid elsewhere (a GPU host); its finished run
    folders, copied into the main results folder, are that grid's runs, finished."""
    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0, 1]") + """
[variants.PEBBLE]
algo = "pebble"
[variants.S-EPOA]
algo = "sepoa"
""")
    elsewhere, here = tmp_path / "gpu-host", tmp_path / "results"
    assert main(["experiment", "run", str(spec_path), "--results", str(elsewhere),
                 "--no-workers", "--variant", "PEBBLE", "--seed", "1"]) == 0
    assert "tiny: 1 runs; 1 enqueued" in capsys.readouterr().out
    url, sessions = sessions_for(elsewhere)
    run_worker(worker_config(url, tmp_path / "data", results_dir=elsewhere, threads=1))
    part = elsewhere / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s1"
    assert json.loads((part / "done.json").read_text())["step"] == 400

    shutil.copytree(part, here / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s1")
    assert main(["experiment", "run", str(spec_path), "--results", str(here),
                 "--no-workers"]) == 0
    assert "tiny: 4 runs; 3 enqueued" in (out := capsys.readouterr().out)
    assert "1 finished before (their folders' results kept)" in out
    _, sessions = sessions_for(here)
    with sessions() as session:
        rows = grid_runs(session, prefix="tiny/")
    assert {k.split("/", 2)[2]: str(r.status) for k, r in rows.items()} == {
        "PEBBLE/eps0.3/s0": "queued", "PEBBLE/eps0.3/s1": "finished",
        "S-EPOA/eps0.3/s0": "queued", "S-EPOA/eps0.3/s1": "queued"}

    # What the spec lacks is said at the door, in one line, and nothing is written.
    for args, message in (
            (["--variant", "SURF"], "spec 'tiny' has no variant 'SURF'; its variants: "
                                    "'PEBBLE', 'S-EPOA'"),
            (["--variant", "PEBBLE", "--seed", "7"], "spec 'tiny' runs none of seeds 7 with "
                                                     "'PEBBLE'")):
        assert main(["experiment", "run", str(spec_path), "--results", str(tmp_path / "none"),
                     "--no-workers", *args]) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "none").exists()


def test_status_counts_a_copied_in_finished_run_of_a_part_not_launched_here(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A finished run folder copied in from another host, of a part no launch here enqueued,
    is finished in `experiment status` (its table and its counts), not "not queued"."""
    from runvocab.config import to_dict

    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0, 1]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    spec = load_spec(spec_path, check=False)
    results = tmp_path / "results"
    copied = next(run for run in spec.runs() if run.seed == 1)
    folder = results / grid_key(spec, copied)
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps(to_dict(copied.config()), default=str))
    (folder / "done.json").write_text(json.dumps({"step": 400}))

    assert main(["experiment", "run", str(spec_path), "--results", str(results),
                 "--no-workers", "--seed", "0"]) == 0
    capsys.readouterr()
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    out = capsys.readouterr().out
    assert "tiny: 2 runs: 1 finished, 1 queued" in out, out
    line = next(x for x in out.splitlines() if x.split()[4:5] == ["1"])
    assert line.split()[5] == "finished" and "done" in line.split(), line

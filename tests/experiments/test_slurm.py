"""The Slurm script as text, and what a user of it meets around it: this `sepoa` by absolute
path, resources sized by the spec's preset, the log appended to on a requeue, the password kept
out of the script, SQLite refused with its reason (or pinned to one node), `experiment status`
showing each run's worker and heartbeat age, and a closed pipe that is not an error. The script
run on a real Slurm: test_slurm_cluster.py."""

from __future__ import annotations

import argparse
import os
import re
import shlex
import stat
import subprocess
import sys
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import select, update

from experiments.launch import run_experiment
from experiments.queue import training_workers
from experiments.slurm import URL_FILE, running_sepoa, seconds
from experiments.spec import load_spec
from labelqueue import Run, claim_run, make_engine, migrate, session_factory
from labelqueue.models import utcnow
from sepoa.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[2]
SPEC = """
name = "tiny"
preset = "{preset}"
steps = 400
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]
threads = 2

[variants.PEBBLE]
algo = "pebble"
"""
SECRET_URL = "postgresql+psycopg://sepoa:hunter2@db.cluster:5432/sepoa"


def spec_file(tmp_path: Path, preset: str = "tiny") -> Path:
    path = tmp_path / f"spec-{preset}.toml"
    path.write_text(SPEC.format(preset=preset))
    return path


def script_of(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    assert main(argv) == 0
    return capsys.readouterr().out


def options(script: str) -> list[str]:
    return [line.split(" ", 1)[1] for line in script.splitlines() if line.startswith("#SBATCH ")]


def worker_args(script: str) -> argparse.Namespace:
    """The worker command the script execs, parsed as `sepoa worker` parses it."""
    command = script[script.index("\nexec ") + 6:].replace("\\\n", " ")
    argv = shlex.split(command.replace('"slurm-${SLURM_ARRAY_JOB_ID}-${SLURM_ARRAY_TASK_ID}"',
                                       "slurm-1-0"))
    assert argv[0] == running_sepoa()[0] and argv[1] == "worker"
    return build_parser("worker").parse_args(argv[1:])


def test_the_script_runs_this_sepoa_and_sizes_each_task_by_the_preset(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    url = "postgresql+psycopg://sepoa@db.cluster/sepoa"  # a password file or trust: no secret
    script = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "8",
                                "--database-url", url, "--results", "/shared/results",
                                "--gpus", "1", "--partition", "gpu"])
    assert script.startswith("#!/bin/bash\n")
    assert subprocess.run(["bash", "-n"], input=script, text=True).returncode == 0
    assert options(script) == [
        "--job-name=sepoa-tiny", "--array=0-7", "--ntasks=1", "--cpus-per-task=2", "--mem=2G",
        "--time=24:00:00", "--signal=B:USR1@300", '--output="/shared/results/slurm-%A_%a.log"',
        "--open-mode=append", "--partition=gpu", "--gres=gpu:1"]
    # The sepoa this command runs, by absolute path: found without activating .venv.
    sepoa = running_sepoa()[0]
    assert os.path.isabs(sepoa) and os.access(sepoa, os.X_OK)
    assert sepoa == str(Path(sys.executable).parent / "sepoa")
    args = worker_args(script)
    assert (args.database_url, args.database_url_file) == (url, None)
    assert (args.results, args.data_dir, args.threads, args.once, args.device, args.worker_id) \
        == ("/shared/results", "/shared/results", 2, True, "cuda", "slurm-1-0")

    # The preset decides the memory; the flags override memory, CPUs, the warning, and ask
    # Slurm to requeue on preemption.
    small = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path, "small")),
                               "--workers", "2", "--database-url", url, "--results", "/r",
                               "--threads", "4", "--mem", "5G", "--time", "20", "--requeue",
                               "--sepoa", "/opt/sepoa/bin/sepoa"])
    assert {"--cpus-per-task=4", "--mem=5G", "--time=20", "--signal=B:USR1@300",
            "--requeue"} <= set(options(small))
    assert "exec /opt/sepoa/bin/sepoa worker" in small
    assert "#SBATCH --mem=3G" in script_of(capsys, [
        "experiment", "slurm", str(spec_file(tmp_path, "small")), "--workers", "2",
        "--database-url", url])
    assert "#SBATCH --mem=8G" in script_of(capsys, [
        "experiment", "slurm", str(spec_file(tmp_path, "paper")), "--workers", "2",
        "--database-url", url])
    # A short time limit: warned a quarter of it ahead.
    assert "#SBATCH --signal=B:USR1@120" in script_of(capsys, [
        "experiment", "slurm", str(spec_file(tmp_path)), "--workers", "1", "--database-url",
        url, "--time", "0:08:00"])
    assert [seconds(t) for t in ("90", "5:30", "2:00:00", "1-12", "1-0:30", "1-00:00:05",
                                 "UNLIMITED")] == [5400, 330, 7200, 129600, 88200, 86405, None]


def test_a_sepoa_named_on_the_nodes_path_runs_and_a_missing_one_is_named(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bin_dir = tmp_path / "my bin"
    bin_dir.mkdir()
    fake = bin_dir / "sepoa"
    fake.write_text('#!/bin/sh\necho "ran: $*"\n')
    fake.chmod(0o755)
    env = {"PATH": f"{bin_dir}:/usr/bin:/bin", "SLURM_ARRAY_JOB_ID": "1",
           "SLURM_ARRAY_TASK_ID": "0", "SLURM_JOB_ID": "1"}
    for sepoa, runs in (("sepoa", True), (shlex.quote(str(fake)), True),
                        ("no-such-sepoa", False)):
        script = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path)),
                                    "--workers", "1", "--database-url",
                                    "postgresql+psycopg://u@h/d", "--results",
                                    str(tmp_path / "r"), "--sepoa", sepoa])
        done = subprocess.run(["bash"], input=script, text=True, capture_output=True, env=env)
        if runs:
            assert done.returncode == 0, done.stderr
            assert done.stdout.splitlines()[-1].startswith("ran: ")
        else:
            assert done.returncode == 127
            assert done.stderr.startswith("error: no-such-sepoa is not found on ")


def test_the_log_path_keeps_a_space_and_a_percent_sign(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path)), "--workers",
                                "1", "--database-url", "postgresql+psycopg://u@h/d",
                                "--results", "/shared/my results/50%"])
    assert '--output="/shared/my results/50%%/slurm-%A_%a.log"' in options(script)
    assert main(["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "1",
                 "--database-url", "postgresql+psycopg://u@h/d", "--results", '/shared/a"b']) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --results '/shared/a\"b': a folder whose path holds a "
                          "double quote")
    assert err.count("\n") == 1


def test_the_password_stays_out_of_the_script_and_the_workers_command_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    results = tmp_path / "shared"
    monkeypatch.setenv("SEPOA_DATABASE_URL", SECRET_URL)  # where a user keeps it
    assert main(["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "2",
                 "--results", str(results)]) == 0
    out = capsys.readouterr()
    assert "hunter2" not in out.out
    assert "# Queue: postgresql+psycopg://sepoa:***@db.cluster:5432/sepoa" in out.out
    kept = results / URL_FILE
    assert f"read the URL from {kept} (mode 600)" in out.err
    assert kept.read_text().strip() == SECRET_URL
    assert stat.S_IMODE(kept.stat().st_mode) == 0o600
    args = worker_args(out.out)
    assert (args.database_url, args.database_url_file) == (None, str(kept))

    # A file the user keeps themselves is named as it is, and read by the workers.
    monkeypatch.delenv("SEPOA_DATABASE_URL")
    own = tmp_path / "queue-url"
    own.write_text(f"# the queue\n{SECRET_URL}\n")
    own.chmod(0o600)
    script = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path)), "--workers",
                                "2", "--database-url-file", str(own)])
    assert worker_args(script).database_url_file == str(own)
    assert "hunter2" not in script
    # ... which other users may not read, as libpq refuses a password file.
    own.chmod(0o644)
    assert main(["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "2",
                 "--database-url-file", str(own)]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: database URL file {own} may be read by other users (mode 644); "
                   f"chmod 600 {own}\n")
    worker = subprocess.run([sys.executable, "-m", "sepoa", "worker",
                             "--database-url-file", str(own)], capture_output=True, text=True,
                            cwd=ROOT, timeout=60)
    assert worker.returncode == 2 and "may be read by other users" in worker.stderr
    assert "hunter2" not in worker.stderr


def test_sqlite_is_refused_with_the_reason_unless_every_task_runs_on_one_node(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = str(spec_file(tmp_path))
    assert main(["experiment", "slurm", spec, "--workers", "2", "--database-url",
                 "sqlite:///q.db"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --database-url: a SQLite queue is a file, and the array's "
                          "tasks are separate jobs that Slurm may place on any node")
    assert "--node NAME" in err and err.count("\n") == 1
    assert main(["experiment", "slurm", spec, "--workers", "2"]) == 2
    assert capsys.readouterr().err.startswith("error: no queue database: give --database-url")

    results = tmp_path / "results"
    script = script_of(capsys, ["experiment", "slurm", spec, "--workers", "2", "--node", "gpu7",
                                "--results", str(results)])
    assert "#SBATCH --nodelist=gpu7" in script
    assert "# Every task runs on gpu7 (--nodelist): the SQLite queue must be on a disk" in script
    # The default queue of `experiment run`, by absolute path.
    assert worker_args(script).database_url == f"sqlite:///{results.absolute() / 'queue.db'}"


@pytest.mark.parametrize(("argv", "message"), [
    (["--time", "soon"], "error: --time 'soon': use minutes, MM:SS, HH:MM:SS or D-HH:MM:SS"),
    (["--signal-before", "0"], "error: --signal-before 0: give at least 1 second and less "
                               "than --time 24:00:00 (86400 s)"),
    (["--signal-before", "900", "--time", "10"], "error: --signal-before 900: give at least 1 "
     "second and less than --time 10 (600 s), or every worker is told to go as it starts; the "
     "default is 150"),
    (["--signal-before", "0", "--time", "unlimited"],
     "error: --signal-before 0: give at least 1 second"),
    (["--database-url", "x", "--database-url-file", "y"],
     "error: give --database-url or --database-url-file, not both"),
])
def test_bad_options_get_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                  argv: list[str], message: str) -> None:
    full = ["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "2"]
    if "--database-url" not in argv:
        full += ["--database-url", "postgresql+psycopg://u@h/d"]
    assert main(full + argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1, err


@pytest.mark.parametrize(("argv", "message"), [
    (["--partition", "gpu\ntouch /tmp/owned"], "error: --partition 'gpu\\ntouch /tmp/owned': "
     "give a Slurm partition name of letters, digits, '_', '-' and '.', or several separated "
     "by commas (gpu,cpu)"),
    (["--partition", "gpu --wrap=id"], "error: --partition 'gpu --wrap=id': give a Slurm "
     "partition name"),
    (["--node", "n1\ntouch /tmp/owned"], "error: --node 'n1\\ntouch /tmp/owned': give one "
     "Slurm node name of letters, digits, '_', '-' and '.' (gpu07)"),
    (["--node", "n[1-4]"], "error: --node 'n[1-4]': give one Slurm node name"),
    (["--mem", "4G --wrap=id"], "error: --mem '4G --wrap=id': give a whole number with a unit "
     "K, M, G or T, such as 4G or 4000M (megabytes without one)"),
    (["--mem", "1.5G"], "error: --mem '1.5G': give a whole number"),
    (["--time", "20\n"], "error: --time '20\\n': use minutes, MM:SS, HH:MM:SS or D-HH:MM:SS"),
    (["--time", "\u0662\u0660"], "error: --time '\u0662\u0660': use minutes"),
    (["--results", "/shared/r\rx"], "error: --results '/shared/r\\rx': a line break or other "
     "control character cannot be written in the script"),
    (["--database-url", "postgresql+psycopg://u:pw@h/d\ntouch /tmp/owned"],
     "error: --database-url 'postgresql+psycopg://u:***@h/d\\ntouch /tmp/owned': a line "
     "break or other control character cannot be written in the script"),
])
def test_a_value_that_would_add_options_or_lines_to_the_script_gets_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
        message: str) -> None:
    """What goes into an #SBATCH line or a comment stays one option of one line: a space would
    hand sbatch options of its own, a line break would add a line that bash runs."""
    full = ["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "2",
            "--results", str(tmp_path / "results")]
    if "--database-url" not in argv:
        full += ["--database-url", "postgresql+psycopg://u@h/d"]
    assert main(full + argv) == 2
    out = capsys.readouterr()
    assert out.out == "" and not (tmp_path / "results").exists()
    assert out.err.startswith(message) and out.err.count("\n") == 1, out.err
    assert "pw" not in out.err


def test_a_url_file_whose_path_holds_a_line_break_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    own = tmp_path / "queue\ntouch owned"
    own.write_text(f"{SECRET_URL}\n")
    own.chmod(0o600)
    assert main(["experiment", "slurm", str(spec_file(tmp_path)), "--workers", "2",
                 "--database-url-file", str(own)]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1
    assert out.err.startswith(f"error: --database-url-file {str(own)!r}: a line break")


def test_valid_slurm_names_and_memory_are_written_as_given(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    script = script_of(capsys, ["experiment", "slurm", str(spec_file(tmp_path)), "--workers",
                                "1", "--database-url", "postgresql+psycopg://u@h/d",
                                "--partition", "gpu,cpu_long", "--node", "gpu-07.cluster",
                                "--mem", "4000M", "--time", "1-00:00:00"])
    assert {"--partition=gpu,cpu_long", "--nodelist=gpu-07.cluster", "--mem=4000M",
            "--time=1-00:00:00"} <= set(options(script))
    assert subprocess.run(["bash", "-n"], input=script, text=True).returncode == 0


def test_status_shows_each_runs_worker_and_heartbeat_age_and_flags_dead_ones(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC.format(preset="tiny").replace("seeds = [0, 1]",
                                                            "seeds = [0, 1, 2, 3]"))
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    url = f"sqlite:///{results / 'queue.db'}"
    migrate(url)
    engine = make_engine(url)
    sessions = session_factory(engine)
    ages = {"alive": 5, "quiet": 100, "gone": 400}
    with sessions() as session:
        for worker, age in ages.items():
            run = claim_run(session, worker_id=worker)
            assert run is not None
            session.execute(update(Run).where(Run.id == run.id).values(
                heartbeat_at=utcnow() - timedelta(seconds=age)))
            session.commit()
    engine.dispose()

    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    table = capsys.readouterr().out
    lines = table.splitlines()
    assert lines[1].split() == ["task", "variant", "eps", "budget", "seed", "status", "step",
                                "worker", "heartbeat", "folder", "left"]
    assert lines[2].split()[5:] == ["running", "0/400", "alive", "5s", "-", "?"]
    assert lines[3].split()[5:] == ["running", "0/400", "quiet", "1m40s", "silent", "-", "?"]
    assert lines[4].split()[5:] == ["running", "0/400", "gone", "6m40s", "DEAD", "-", "?"]
    assert lines[5].split()[5:] == ["queued", "0/400", "-", "-", "-", "?"]
    assert lines[6].startswith("time left (estimated): 4 run(s) without an estimate yet")
    assert lines[7] == "workers gone silent:"
    assert re.fullmatch(r"  tiny/dmc-cheetah_run/PEBBLE/eps0\.3/s1: worker quiet silent for "
                        r"1m4\ds: stopped or dead\? Another worker may take the run over in "
                        r"3m[12]\ds unless it comes back", lines[8]), lines[8]
    assert lines[9:] == [
        "  tiny/dmc-cheetah_run/PEBBLE/eps0.3/s2: worker gone silent for 6m40s, presumed dead: "
        "the next worker to look takes the run over from its checkpoint"]
    # The time left is divided among the workers training now: neither "gone" nor "quiet",
    # which may have been killed a moment ago.
    with session_factory(make_engine(url))() as session:
        rows = session.scalars(select(Run)).all()
        assert training_workers(rows, utcnow()) == {"alive"}


def test_a_closed_standard_output_is_not_an_error(tmp_path: Path) -> None:
    """`sepoa experiment run ... | head -1`: the command does its work and says nothing more,
    rather than blaming the results folder for a broken pipe."""
    spec = spec_file(tmp_path)
    results = tmp_path / "results"
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader has gone before the first line
    try:
        for argv in (["run", "--no-workers"], ["status"]):
            done = subprocess.run(
                [sys.executable, "-m", "sepoa.cli", "experiment", argv[0], str(spec),
                 "--results", str(results), *argv[1:]],
                stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=ROOT, timeout=60,
                env=os.environ | {"SEPOA_DATABASE_URL": ""})
            assert (done.returncode, done.stderr) == (0, ""), argv
    finally:
        os.close(write_end)
    assert (results / "queue.db").exists() and (results / "tiny" / "spec.toml").exists()


def test_the_docs_step_by_step_keeps_the_password_out_of_the_jobs_environment() -> None:
    """sbatch saves the environment it runs in into the job, and each task's process shows it:
    the documented steps name the URL's file, never the URL."""
    docs = (ROOT / "docs" / "EXPERIMENTS.md").read_text()
    block = docs.split("Step by step, with the URL", 1)[1].split("```", 2)[1]
    commands = " ".join(block.replace("\\\n", " ").splitlines())
    assert "SEPOA_DATABASE_URL=" not in commands and "sbatch workers.sbatch" in commands
    sepoa = commands.split(".venv/bin/sepoa ")[1:]
    assert len(sepoa) == 3 and all("--database-url-file " in c for c in sepoa), sepoa

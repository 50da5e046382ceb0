"""`sepoa experiment run --mps`: a Multi-Process Service daemon of the launcher's own, started
before its workers and told to quit after them. Checked here with a stand-in for
`nvidia-cuda-mps-control` that records how it was called; on a GPU host,
`benchmarks/gpu_check.sh tf32learn` runs the real one."""

from __future__ import annotations

import functools
import os
import time
from pathlib import Path

import pytest

from experiments.launch import run_experiment
from experiments.mps import MpsError, check_available, mps_daemon
from experiments.spec import load_spec
from sepoa.cli import main
from sepoa.experiment_commands import train_locally

FAKE = """#!/bin/bash
# stands in for nvidia-cuda-mps-control: one line per call, with its pipe folder and input
input=$( [ "$1" = -d ] || cat )
there=$(test -d "$CUDA_MPS_PIPE_DIRECTORY" && echo yes)
echo "$* | $CUDA_MPS_PIPE_DIRECTORY | $input | pipe folder there: $there" >> {log}
[ {status} = 0 ] || echo "An instance of this daemon is already running" >&2
exit {status}
"""


def fake_control(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, status: int = 0) -> Path:
    bin_dir, log = tmp_path / "bin", tmp_path / "control.log"
    bin_dir.mkdir()
    program = bin_dir / "nvidia-cuda-mps-control"
    program.write_text(FAKE.format(log=log, status=status))
    program.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return log


def tiny_spec(tmp_path: Path) -> Path:
    path = tmp_path / "spec.toml"
    path.write_text('name = "tiny"\npreset = "tiny"\nsteps = 200\ntasks = ["dmc:cheetah_run"]\n'
                    'eps = [0.3]\nseeds = [0]\n[variants.SAC]\nalgo = "sac"\n')
    return path


def test_the_daemon_runs_for_the_block_in_a_folder_of_its_own(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = fake_control(tmp_path, monkeypatch)
    with mps_daemon(tmp_path / "mps") as env:
        pipe = env["CUDA_MPS_PIPE_DIRECTORY"]
        assert Path(pipe).is_dir() and env["CUDA_MPS_LOG_DIRECTORY"] == str(tmp_path / "mps")
        assert log.read_text().splitlines() == [f"-d | {pipe} |  | pipe folder there: yes"]
    assert log.read_text().splitlines()[1] == f" | {pipe} | quit | pipe folder there: yes"
    assert not Path(pipe).exists()  # the pipe's folder goes with the daemon, the log stays
    assert (tmp_path / "mps").is_dir()


def test_a_daemon_that_keeps_its_output_open_does_not_hold_the_launcher(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_control(tmp_path, monkeypatch)
    program = tmp_path / "bin" / "nvidia-cuda-mps-control"
    # As a daemon may: a child that lives on with the caller's standard output.
    lives_on = '[ "$1" = -d ] && sleep 30 &\nexit 0'
    program.write_text(program.read_text().replace("exit 0", lives_on))
    start = time.monotonic()
    with mps_daemon(tmp_path / "mps"):
        assert time.monotonic() - start < 10


def test_a_daemon_that_does_not_start_is_said_in_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_control(tmp_path, monkeypatch, status=1)
    with pytest.raises(MpsError, match=r"-d exited with status 1: An instance of this daemon "
                       "is already running"), mps_daemon(tmp_path / "mps"):
        pass
    monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))
    with pytest.raises(MpsError, match="is not on the PATH"):
        check_available()


def test_the_launcher_starts_the_daemon_before_its_workers_and_stops_it_after(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = fake_control(tmp_path, monkeypatch)
    spec_path = tiny_spec(tmp_path)
    lines: list[str] = []
    results = tmp_path / "results"
    assert run_experiment(load_spec(spec_path), results=results, workers=1, threads=1,
                          echo=lines.append,
                          train=functools.partial(train_locally, mps=True)) == 0
    started = next(i for i, line in enumerate(lines) if line.startswith("MPS daemon started"))
    assert started < next(i for i, line in enumerate(lines) if "-exp-0 started" in line)
    calls = log.read_text().splitlines()
    assert [c.split(" | ")[0] for c in calls] == ["-d", ""] and "quit" in calls[1]
    assert (results / "tiny" / "dmc-cheetah_run" / "SAC" / "eps0.3" / "s0" / "done.json").exists()


def test_mps_without_a_gpu_device_is_refused_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tiny_spec(tmp_path)
    for extra in ([], ["--device", "cpu"], ["--no-workers"]):
        assert main(["experiment", "run", str(spec_path), "--results",
                     str(tmp_path / "results"), "--mps", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "--mps is for local workers on a GPU" in err
    assert not (tmp_path / "results").exists()

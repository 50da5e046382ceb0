"""CUDA's Multi-Process Service for a launcher's local workers (`sepoa experiment run --mps`).

Without it, the processes of several runs on one GPU take turns on it (time-slicing between
their contexts); with it, their kernels share one context. Measured on an H200 with 4
paper-preset PEBBLE runs: 2.87x one run's steps/s under MPS, 1.33x without
(benchmarks/README.md, `gpu_check.sh mps`).

The daemon is a user-space process with its own pipe and log folders, made for this launch, so
it neither needs nor touches the GPU's settings (compute mode, MIG) or another user's daemon.
The workers find it through `CUDA_MPS_PIPE_DIRECTORY` in their environment; `quit` stops it
when the launcher ends.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CONTROL = "nvidia-cuda-mps-control"


class MpsError(RuntimeError):
    """The daemon could not be started; the message says why."""


def check_available() -> None:
    """MpsError unless the MPS control program is on the PATH."""
    if shutil.which(CONTROL) is None:
        raise MpsError(f"--mps: {CONTROL} is not on the PATH (it comes with the NVIDIA "
                       "driver); leave --mps out to let the workers share the GPU by "
                       "time-slicing")


@contextmanager
def mps_daemon(log_dir: Path) -> Iterator[dict[str, str]]:
    """Start a daemon for the duration of the block, its logs in `log_dir` (control.log has a
    line for each client, that is each worker that went through it); yields the environment
    the workers need."""
    check_available()
    # A short folder: the daemon's pipe is a Unix socket, whose path is limited to ~100 bytes.
    folder = tempfile.mkdtemp(prefix="sepoa-mps-")
    log_dir.mkdir(parents=True, exist_ok=True)
    env = {"CUDA_MPS_PIPE_DIRECTORY": folder, "CUDA_MPS_LOG_DIRECTORY": str(log_dir)}
    # Its output to a file, not a pipe: a daemon that kept the pipe open would hold `run`
    # until it exits.
    start_log = log_dir / "start.txt"
    with start_log.open("w") as out:
        started = subprocess.run([CONTROL, "-d"], env=os.environ | env, stdout=out,
                                 stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    if started.returncode != 0:
        shutil.rmtree(folder, ignore_errors=True)
        said = start_log.read_text().strip().splitlines()
        raise MpsError(f"--mps: {CONTROL} -d exited with status {started.returncode}"
                       + (f": {said[-1]}" if said else ""))
    try:
        yield env
    finally:
        with (log_dir / "quit.txt").open("w") as out:
            subprocess.run([CONTROL], input=b"quit\n", env=os.environ | env, stdout=out,
                           stderr=subprocess.STDOUT, timeout=60)
        shutil.rmtree(folder, ignore_errors=True)

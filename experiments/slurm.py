"""`sepoa experiment slurm`: an sbatch array script whose tasks are `sepoa worker --once`.

    sepoa experiment run SPEC --no-workers --results /shared/results      # enqueue
    sepoa experiment slurm SPEC --workers 8 --results /shared/results > workers.sbatch
    sbatch workers.sbatch

(the queue's URL in SEPOA_DATABASE_URL, or --database-url / --database-url-file, for both.)

The script runs as printed on a node that sees the same files: it calls this very `sepoa` by
its absolute path (`--sepoa` to name another: a path, or a command on the nodes' PATH), asks
for the CPUs of the spec's `threads` and the memory its preset needs (`PRESET_MEMORY`;
`--threads`, `--mem` to change), appends to its log on a requeue (`--open-mode=append`), and is
requeued by Slurm on preemption or node failure when asked (`--requeue`). Each array task is
one worker named after the job and its index; it claims the queue's runs until none is waiting
and exits. On SIGTERM (`scancel`, preemption) or SIGUSR1 (sent `signal_before` seconds ahead of
the time limit, `--signal=B:USR1@...`), the worker checkpoints its run at the end of the
episode and releases it: the next worker, or the task requeued under the same name, resumes it
from that checkpoint as soon as it starts.

No secret is written into the script: a URL without a password is written as it is; a URL with
one is read by the tasks from a file of mode 600 (the one given with --database-url-file, or
`<results>/.sepoa-database-url`, written by the command), so it shows neither in the script nor
in `ps` on the nodes; every log line shows the URL masked.

The queue must be a database server every node reaches (PostgreSQL). A SQLite file is refused,
since array tasks are separate jobs placed on any node and SQLite's locking is not safe on the
network filesystems nodes share, unless every task is pinned to one node (`node`): then the
file must be on that node's own disk. No Slurm module is needed to write the script: the
cluster runs it.
"""

from __future__ import annotations

import os
import re
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from experiments.spec import Spec

PRESET_MEMORY = {"tiny": "2G", "small": "3G", "paper": "8G"}
"""memory per task by the spec's preset: a tiny run's worker peaks at about 0.5 GB (measured),
a small one's replay buffer of 200 k transitions adds tens of MB, the paper's 1 M transitions
up to 0.7 GB per copy on quadruped (a checkpoint writes a second one), with CUDA's host memory"""
SIGNAL_BEFORE_S = 300
"""how long before the time limit Slurm warns a worker (SIGUSR1), at most; a quarter of a
shorter time limit. An episode ends and a checkpoint is written well within it."""
URL_FILE = ".sepoa-database-url"
"""where `sepoa experiment slurm` keeps a URL that holds a password, under the results folder"""


class SlurmError(ValueError):
    """An option the script cannot be written with; the message says which and why."""


@dataclass(frozen=True)
class QueueAccess:
    """How the array's tasks reach the queue, with no secret in the script."""

    shown: str
    """the URL with its password masked, for the script's comment"""
    url: str | None = None
    """a URL without a password, passed to the workers as it is"""
    url_file: Path | None = None
    """a file (mode 600) holding the URL, passed to the workers by its path"""


def seconds(time_limit: str) -> int | None:
    """A Slurm time limit in seconds (None for infinite / unlimited): minutes, MM:SS, HH:MM:SS,
    D-HH, D-HH:MM or D-HH:MM:SS. SlurmError for anything else."""
    if time_limit.lower() in ("infinite", "unlimited"):
        return None
    days, hours, minutes, secs = 0, 0, 0, 0
    # As written into the script: no space or line break around it, ASCII digits only.
    match = re.fullmatch(r"(?:([0-9]+)-)?([0-9]+)(?::([0-9]+))?(?::([0-9]+))?", time_limit)
    if match is None:
        raise SlurmError(f"--time {time_limit!r}: use minutes, MM:SS, HH:MM:SS or D-HH:MM:SS")
    d, a, b, c = match.groups()
    if d is not None:  # D-HH[:MM[:SS]]
        days, hours, minutes, secs = int(d), int(a), int(b or 0), int(c or 0)
    elif c is not None:  # HH:MM:SS
        hours, minutes, secs = int(a), int(b), int(c)
    elif b is not None:  # MM:SS
        minutes, secs = int(a), int(b)
    else:  # minutes
        minutes = int(a)
    total = ((days * 24 + hours) * 60 + minutes) * 60 + secs
    if total <= 0:
        raise SlurmError(f"--time {time_limit!r}: the time limit must be above zero")
    return total


def default_memory(spec: Spec) -> str:
    return PRESET_MEMORY.get(spec.preset, PRESET_MEMORY["paper"])


def default_signal_before(time_limit: str) -> int:
    limit = seconds(time_limit)
    return SIGNAL_BEFORE_S if limit is None else max(1, min(SIGNAL_BEFORE_S, limit // 4))


def signal_before_for(time_limit: str, signal_before: int | None) -> int:
    """How long before the time limit the workers are warned: `signal_before`, else the
    default. SlurmError for a bad --time, or a warning due as the task starts."""
    if signal_before is None:
        return default_signal_before(time_limit)
    limit = seconds(time_limit)
    if limit is None and signal_before < 1:
        raise SlurmError(f"--signal-before {signal_before}: give at least 1 second")
    if limit is not None and not 1 <= signal_before < limit:
        raise SlurmError(
            f"--signal-before {signal_before}: give at least 1 second and less than --time "
            f"{time_limit} ({limit} s), or every worker is told to go as it starts; the "
            f"default is {default_signal_before(time_limit)}")
    return signal_before


def running_sepoa() -> list[str]:
    """The command that runs this `sepoa`, by absolute path: the script it was started as, else
    the `sepoa` beside this Python (a virtual environment's bin folder, not activated), else
    this Python with `-m sepoa.cli`."""
    started = Path(sys.argv[0]) if sys.argv and sys.argv[0] else None
    if started is not None and started.name == "sepoa" and os.access(started, os.X_OK):
        return [str(started.absolute())]
    beside = Path(sys.executable).parent / "sepoa"  # not resolved: a venv's python is a link
    if beside.is_file() and os.access(beside, os.X_OK):
        return [str(beside.absolute())]
    return [str(Path(sys.executable).absolute()), "-m", "sepoa.cli"]


def write_url_file(results: Path, url: str) -> Path:
    """Keep `url` in `<results>/.sepoa-database-url`, readable by its owner only."""
    results.mkdir(parents=True, exist_ok=True)
    path = results / URL_FILE
    tmp = path.with_name(f"{URL_FILE}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(url + "\n")
    os.replace(tmp, path)
    return path


SLURM_NAME = r"[A-Za-z0-9][A-Za-z0-9_.-]*"
"""a partition's or a node's name as the script writes it: nothing sbatch or bash reads as
anything but the name (no space, quote, `#`, `$` or line break)"""


def check_options(*, partition: str | None = None, node: str | None = None,
                  memory: str | None = None) -> None:
    """SlurmError, saying what is valid, for a value the script could not hold as one #SBATCH
    option: a space would add options of the user's to sbatch's, a line break lines to the
    script that bash runs."""
    if partition is not None and not re.fullmatch(rf"{SLURM_NAME}(,{SLURM_NAME})*", partition):
        raise SlurmError(f"--partition {partition!r}: give a Slurm partition name of letters, "
                         "digits, '_', '-' and '.', or several separated by commas (gpu,cpu)")
    if node is not None and not re.fullmatch(SLURM_NAME, node):
        raise SlurmError(f"--node {node!r}: give one Slurm node name of letters, digits, '_', "
                         "'-' and '.' (gpu07)")
    if memory is not None and not re.fullmatch(r"[0-9]+[KMGTkmgt]?", memory):
        raise SlurmError(f"--mem {memory!r}: give a whole number with a unit K, M, G or T, "
                         "such as 4G or 4000M (megabytes without one)")


def check_shown(option: str, text: str) -> None:
    """SlurmError for a value shown in the script's comments that holds a control character:
    a line break there would start a line of its own, which bash runs."""
    if any(ord(char) < 32 or ord(char) == 127 for char in text):
        raise SlurmError(f"{option} {text!r}: a line break or other control character cannot "
                         "be written in the script; use one without")


def sbatch_path(path: Path) -> str:
    """`path` for a double-quoted #SBATCH value (sbatch splits its lines at spaces): `%`, which
    starts a filename pattern there, written `%%`. SlurmError for a path that cannot be
    written so."""
    text = str(path)
    check_shown("--results", text)
    if '"' in text:
        raise SlurmError(f"--results {text!r}: a folder whose path holds a double quote cannot "
                         "be written in the script; use another one")
    return text.replace("%", "%%")


def sbatch_script(spec: Spec, *, workers: int, queue: QueueAccess, results: Path,
                  threads: int | None = None, time_limit: str = "24:00:00",
                  partition: str | None = None, gpus: int = 0, memory: str | None = None,
                  sepoa: Sequence[str] | None = None, requeue: bool = False,
                  node: str | None = None, signal_before: int | None = None) -> str:
    """The script's text: an array of `workers` tasks of one worker each, `threads` CPUs and
    torch threads per task (default the spec's), `memory` per task (default by the spec's
    preset), `gpus` GPUs per task, `node` to pin every task to one node."""
    check_options(partition=partition, node=node, memory=memory)
    check_shown("--database-url", queue.shown)
    if queue.url_file is not None:
        check_shown("--database-url-file", str(queue.url_file))
    threads = threads or spec.threads
    memory = memory or default_memory(spec)
    before = signal_before_for(time_limit, signal_before)
    sepoa = list(sepoa) if sepoa else running_sepoa()
    results = results.absolute()
    options = [f"--job-name=sepoa-{spec.name}", f"--array=0-{workers - 1}",
               "--ntasks=1", f"--cpus-per-task={threads}", f"--mem={memory}",
               f"--time={time_limit}", f"--signal=B:USR1@{before}",
               f'--output="{sbatch_path(results)}/slurm-%A_%a.log"', "--open-mode=append"]
    if requeue:
        options.append("--requeue")
    if partition:
        options.append(f"--partition={partition}")
    if gpus:
        options.append(f"--gres=gpu:{gpus}")
    if node:
        options.append(f"--nodelist={node}")
    if queue.url_file is not None:
        where = ["--database-url-file", str(queue.url_file)]
        told = f"the tasks read it from {queue.url_file}, mode 600"
    else:
        assert queue.url is not None
        where = ["--database-url", queue.url]
        told = "it holds no password"
    command = [*sepoa, "worker", *where, "--data-dir", str(results), "--results", str(results),
               "--threads", str(threads), "--once"]
    if gpus:
        command += ["--device", "cuda"]
    worker = " ".join(shlex.quote(part) for part in command)
    memory_note = ("--mem" if memory != default_memory(spec) else
                   f"the {spec.preset!r} preset's; --mem to change it")
    runs = len(spec.runs())
    counted = f"{runs} run{'s' if runs != 1 else ''}, preset {spec.preset!r}"
    header = f"""\
# Workers for the experiment {spec.name!r} ({counted}),
# made by `sepoa experiment slurm`. Enqueue the grid first (`sepoa experiment run SPEC
# --no-workers`, same queue and --results), submit with `sbatch <this file>`, and follow it
# with `sepoa experiment status SPEC --results {results}`.
# Each task is one worker, `sepoa worker --once` named slurm-<job>-<task>: it trains queued
# runs until none is left. On SIGTERM (scancel, preemption) or SIGUSR1 ({before} s before the
# time limit) it checkpoints its run at the end of the episode and releases it at once: the
# next worker, or this task requeued, resumes it from there.
# Queue: {queue.shown}
# ({told}).
# Memory per task: {memory} ({memory_note})."""
    pinned = f"""\
# Every task runs on {node} (--nodelist): the SQLite queue must be on a disk of {node}'s own
# (SQLite's locking is not safe on a network filesystem)."""
    lines = ["#!/bin/bash", header, *([pinned] if node else []),
             *(f"#SBATCH {option}" for option in options),
             "set -euo pipefail",
             # A path or a name on the node's PATH (`--sepoa sepoa`) alike.
             f"if ! command -v -- {shlex.quote(sepoa[0])} >/dev/null; then",
             f"    echo {shlex.quote(f'error: {sepoa[0]} is not found on ')}\"$(hostname)\""
             + shlex.quote(": install the project at the same path on every node, or give "
                           "--sepoa") + " >&2",
             "    exit 127",
             "fi",
             f"export OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}",
             "export MUJOCO_GL=${MUJOCO_GL:-egl}",
             'echo "[slurm] job ${SLURM_JOB_ID}, array task ${SLURM_ARRAY_JOB_ID}_'
             '${SLURM_ARRAY_TASK_ID} on $(hostname), start $((${SLURM_RESTART_COUNT:-0} + 1)),'
             ' $(date -u +%FT%TZ)"',
             f"exec {worker} \\",
             '    --worker-id "slurm-${SLURM_ARRAY_JOB_ID}-${SLURM_ARRAY_TASK_ID}"',
             ""]
    return "\n".join(lines)

"""`sepoa experiment slurm`: an sbatch array script whose tasks are `sepoa worker --once`.

    sepoa experiment run SPEC --no-workers --database-url postgresql+psycopg://...  # enqueue
    sepoa experiment slurm SPEC --workers 8 --database-url postgresql+psycopg://... \\
        --results /shared/results > workers.sbatch && sbatch workers.sbatch

Each array task is one worker named after the job and its index; it claims the queue's runs
until none is waiting and exits. A task killed by the scheduler (time limit, preemption) leaves
its run to the next worker that claims it once its heartbeat is old (`DEAD_WORKER_AFTER_S`),
which resumes it from the run's checkpoint in the shared results folder. No Slurm module is
needed to write the script: the cluster runs it.
"""

from __future__ import annotations

import shlex
from pathlib import Path

from experiments.spec import Spec


def sbatch_script(spec: Spec, *, workers: int, database_url: str, results: Path,
                  threads: int | None = None, time_limit: str = "24:00:00",
                  partition: str | None = None, gpus: int = 0, memory: str = "16G",
                  python: str = "sepoa") -> str:
    """The script's text: an array of `workers` tasks of one worker each, `threads` CPUs and
    torch threads per task (default the spec's), `gpus` GPUs per task."""
    threads = threads or spec.threads
    options = [f"--job-name=sepoa-{spec.name}", f"--array=0-{workers - 1}",
               "--ntasks=1", f"--cpus-per-task={threads}", f"--mem={memory}",
               f"--time={time_limit}",
               f"--output={results / 'slurm-%A_%a.log'}"]
    if partition:
        options.append(f"--partition={partition}")
    if gpus:
        options.append(f"--gres=gpu:{gpus}")
    command = [python, "worker", "--database-url", database_url, "--data-dir", str(results),
               "--results", str(results), "--threads", str(threads), "--once"]
    if gpus:
        command += ["--device", "cuda"]
    worker = " ".join(shlex.quote(part) for part in command)
    lines = ["#!/bin/bash",
             f"# Workers for the experiment {spec.name!r} ({len(spec.runs())} runs), made by",
             "# `sepoa experiment slurm`. Enqueue the grid first (sepoa experiment run SPEC",
             "# --no-workers with the same --database-url); submit with `sbatch <this file>`.",
             *(f"#SBATCH {option}" for option in options),
             "set -euo pipefail",
             f"export OMP_NUM_THREADS={threads} MKL_NUM_THREADS={threads}",
             "export MUJOCO_GL=${MUJOCO_GL:-egl}",
             f"exec {worker} \\",
             '    --worker-id "slurm-${SLURM_ARRAY_JOB_ID}-${SLURM_ARRAY_TASK_ID}"',
             ""]
    return "\n".join(lines)

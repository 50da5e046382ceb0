"""Does a change to the training loop keep every algorithm's behaviour? Trains one tiny run per
algorithm (cheetah_run, scripted teacher at eps 0.3, evaluations and rounds included) and writes
what each run did, without its timings: the episode, evaluation and round rows, and every label.
Run it in two checkouts and compare the folders; a run is deterministic, so a refactoring that
keeps the behaviour leaves them identical.

    .venv/bin/python benchmarks/behaviour_check.py /tmp/after
    (cd ../before && .venv/bin/python benchmarks/behaviour_check.py /tmp/before)
    diff -r --exclude=runs /tmp/before /tmp/after && echo same

About two minutes per checkout on 2 cores.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from runvocab.config import build_config  # noqa: E402
from runvocab.names import ALGOS  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402

TIMINGS = ("fps", "seconds", "answered_at", "shown_at")


def _timing(key: str) -> bool:
    """A wall-time column (the loop's phase seconds included), left out of the fingerprint."""
    return key in TIMINGS or key.startswith("seconds_") or key.endswith("_seconds")


def fingerprint(out: str, algo: str, steps: int) -> None:
    run_dir = os.path.join(out, "runs", algo)
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": algo, "steps": steps, "threads": 1, "teacher.eps": 0.3, "eval_every": 600,
        "run_dir": run_dir, "skill.snapshot_dir": os.path.join(out, "runs", "snapshots")})
    TrainingRun(cfg, progress=False).train()
    for stream in ("episodes", "eval", "rounds"):
        path = os.path.join(run_dir, f"{stream}.csv")
        if os.path.exists(path):
            with open(path, newline="") as f:
                rows = [{k: v for k, v in row.items() if not _timing(k)}
                        for row in csv.DictReader(f)]
            _write_lines(os.path.join(out, f"{algo}-{stream}.jsonl"), rows)
    labels = os.path.join(run_dir, "labels.jsonl")
    if os.path.exists(labels):
        with open(labels) as f:
            rows = [{k: v for k, v in json.loads(line).items() if not _timing(k)}
                    for line in f]
        _write_lines(os.path.join(out, f"{algo}-labels.jsonl"), rows)


def _write_lines(path: str, rows: list[dict]) -> None:
    with open(path, "w") as f:
        f.writelines(json.dumps(row, sort_keys=True) + "\n" for row in rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="a new folder for the fingerprints")
    parser.add_argument("--steps", type=int, default=1400, help="steps per run (tiny preset)")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS),
                        help="the algorithms to run (default: all six)")
    args = parser.parse_args()
    if os.path.exists(args.out):
        parser.error(f"{args.out} exists; give a new folder")
    for algo in args.algos:
        fingerprint(args.out, algo, args.steps)
        print(f"{algo}: done", flush=True)


if __name__ == "__main__":
    main()

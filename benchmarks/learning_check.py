"""Learning check: PEBBLE with a scripted teacher against the SAC oracle at the same steps.

Runs both as `sepoa train` subprocesses side by side (one torch thread each), then prints the
evaluation returns of both at every evaluation step and the final ratio.

    .venv/bin/python benchmarks/learning_check.py --task dmc:cheetah_run --preset small \
        --steps 100000 --eps 0 --out results/learning_check
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import time


def _evals(run_dir: str) -> dict[int, float]:
    path = os.path.join(run_dir, "eval.csv")
    if not os.path.exists(path):
        return {}
    with open(path, newline="") as f:
        return {int(r["step"]): float(r["return"]) for r in csv.DictReader(f)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="dmc:cheetah_run")
    p.add_argument("--preset", default="small")
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--eps", type=float, default=0.0, help="noisy teacher's eps (0 = ideal)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="results/learning_check")
    p.add_argument("--resume", action="store_true", help="continue both runs")
    args = p.parse_args()

    common = ["--task", args.task, "--preset", args.preset, "--steps", str(args.steps),
              "--seed", str(args.seed), "--threads", "1", "--no-progress"]
    runs = {
        "pebble": common + ["--algo", "pebble", "--teacher", "noisy", "--eps", str(args.eps)],
        "sac": common + ["--algo", "sac"],
    }
    procs, start = {}, time.time()
    for name, flags in runs.items():
        run_dir = os.path.join(args.out, name)
        cmd = [sys.executable, "-m", "sepoa", "train", "--run-dir", run_dir, *flags]
        if args.resume:
            cmd = [sys.executable, "-m", "sepoa", "train", "--run-dir", run_dir,
                   "--resume", "--no-progress", "--steps", str(args.steps)]
        os.makedirs(args.out, exist_ok=True)
        log = open(os.path.join(args.out, f"{name}.log"), "a")
        procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
    codes = {name: proc.wait() for name, proc in procs.items()}
    minutes = (time.time() - start) / 60
    if any(codes.values()):
        sys.exit(f"a run failed: {codes} (logs in {args.out})")

    pebble, sac = _evals(os.path.join(args.out, "pebble")), _evals(os.path.join(args.out, "sac"))
    print(f"{args.task}, preset {args.preset}, seed {args.seed}, teacher eps {args.eps}, "
          f"{args.steps} steps, {minutes:.0f} min wall for both")
    print(f"{'step':>8} {'PEBBLE':>9} {'SAC oracle':>11}")
    nan = float("nan")
    for step in sorted(set(pebble) | set(sac)):
        print(f"{step:>8} {pebble.get(step, nan):>9.1f} {sac.get(step, nan):>11.1f}")
    last = max(set(pebble) & set(sac))
    ratio = pebble[last] / sac[last]
    print(f"final: PEBBLE {pebble[last]:.1f} / SAC {sac[last]:.1f} = {ratio:.2f}")


if __name__ == "__main__":
    main()

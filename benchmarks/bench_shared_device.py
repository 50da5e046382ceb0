"""Aggregate environment steps per second of N runs sharing one device, against one run alone:
`sepoa experiment run --device D --workers N` on a spec of N copies of one run (seeds 0 to
N - 1), for each N asked for.

    .venv/bin/python benchmarks/bench_shared_device.py --device cpu --preset tiny --steps 2000 \
        --workers 1,2 --threads 1
    python3 benchmarks/bench_shared_device.py --device cuda --preset paper --algo pebble \
        --steps 10000 --from-step 6000 --workers 1,4 --threads 2

Each N trains in a results folder of its own, from nothing, through the queue and the workers
that `experiment run` starts (as a grid trains). A run's rate is its steps over its episode
rows' wall time after `--from-step` (benchmarks/run_profile.py), so start-up and the steps
before the window are left out; the aggregate is the sum of the concurrent runs' rates, and
beside it the launch's own figure (all steps over the command's wall time, start-up included).
Printed per N: the aggregate, its ratio to N = 1, each run's rate and the update share.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from run_profile import profile  # noqa: E402

SPEC = """name = "shared-device"
preset = "{preset}"
steps = {steps}
tasks = ["{task}"]
eps = [0.3]
seeds = {seeds}
threads = {threads}

[overrides]
{overrides}
[variants.run]
algo = "{algo}"
"""


def counts(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give worker counts such as 1,4") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: every worker count must be at least 1")
    return values


def toml_value(text: str) -> str:
    """A --set value as TOML: numbers and booleans as they are, anything else quoted."""
    if text in ("true", "false"):
        return text
    try:
        float(text)
        return text
    except ValueError:
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def train(n: int, args: argparse.Namespace, folder: Path) -> tuple[float, list[Path]]:
    """Train n copies at once; the launch's wall seconds and the runs' folders."""
    overrides = "".join(f'"{key}" = {toml_value(value)}\n' for key, _, value in
                        (pair.partition("=") for pair in args.set))
    spec = folder / "spec.toml"
    spec.write_text(SPEC.format(preset=args.preset, steps=args.steps, task=args.task,
                                seeds=list(range(n)), threads=args.threads,
                                overrides=overrides, algo=args.algo))
    command = [sys.executable, "-m", "sepoa", "experiment", "run", str(spec), "--results",
               str(folder / "results"), "--workers", str(n), "--threads", str(args.threads),
               "--device", args.device]
    env = os.environ | {"PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"error: {n} worker(s): experiment run exited {done.returncode}:\n"
                         f"{done.stdout[-2000:]}{done.stderr[-2000:]}")
    runs = sorted(p.parent for p in (folder / "results" / "shared-device").rglob("done.json"))
    if len(runs) != n:
        raise SystemExit(f"error: {n} worker(s) finished {len(runs)} run(s); see {folder}")
    return wall, runs


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu", help="auto | cpu | cuda | cuda:N")
    p.add_argument("--workers", type=counts, default=[1, 2], help="worker counts, e.g. 1,4,8")
    p.add_argument("--task", default="dmc:cheetah_run")
    p.add_argument("--preset", default="tiny", choices=("paper", "small", "tiny"))
    p.add_argument("--algo", default="pebble")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads per worker")
    p.add_argument("--from-step", type=int, default=0,
                   help="time only episodes ending after this step (e.g. after round 0)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other config field for every run, e.g. sac.cuda_graph=true")
    args = p.parse_args()
    if any("=" not in pair for pair in args.set):
        raise SystemExit("error: --set takes KEY=VALUE")
    top = Path(tempfile.mkdtemp(prefix="bench-shared-device-"))
    print(f"{args.task} {args.algo} ({args.preset}), {args.steps} steps per run on "
          f"{args.device}, {args.threads} thread(s) per worker, timed after step "
          f"{args.from_step}; folder {top}")
    print(f"{'workers':>7} {'aggregate steps/s':>18} {'vs 1':>6} {'launch steps/s':>15}   "
          "each run's steps/s (updates share)")
    single = None
    for n in args.workers:
        folder = top / f"workers-{n}"
        folder.mkdir()
        began = time.strftime("%H:%M:%S")
        wall, runs = train(n, args, folder)
        # To line up with a GPU utilisation log (gpu_check.sh samples one beside this command).
        print(f"        ({n} worker(s) trained {began} to {time.strftime('%H:%M:%S')})",
              file=sys.stderr)
        rates, shares = [], []
        for run in runs:
            steps, seconds = profile(str(run), args.from_step)
            if not seconds["total"]:
                raise SystemExit(f"error: {run} has no timed episode rows after step "
                                 f"{args.from_step}")
            rates.append(steps / seconds["total"])
            shares.append(seconds["updates"] / seconds["total"])
        aggregate = sum(rates)
        single = single or (aggregate if n == 1 else None)
        ratio = f"{aggregate / single:5.2f}x" if single else "     -"
        each = "  ".join(f"{r:.1f} ({s:.0%})" for r, s in zip(rates, shares, strict=True))
        print(f"{n:>7} {aggregate:>18.1f} {ratio:>6} {n * args.steps / wall:>15.1f}   {each}")
    if single is None:
        print("(no N = 1 among --workers: no ratio)")
    else:
        print(f"one run alone: {single:.1f} steps/s; "
              f"per-run rates at the last N: median {statistics.median(rates):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""A grid's throughput on one device, measured per algorithm and task at N runs sharing it,
and the grid's projected wall time from those figures.

    python3 benchmarks/grid_throughput.py measure specs/paper/dmc-grid.toml --device cuda \
        --workers 1,4,8 --out OUT [--tasks dmc:cheetah_run] [--budget-seconds 480]
    python3 benchmarks/grid_throughput.py project specs/paper/dmc-grid.toml OUT/throughput.csv \
        --workers 8 [--pretrain-steps-per-s X]

`measure` runs, for each task and variant of the spec (spec order) and each N, N copies of the
variant's run sharing the device (`bench_shared_device.py`, through `sepoa experiment run`, the
grid's own path; under MPS when the caller started its daemon, as `gpu_check.sh grid` does),
and times steps `LEARNING_FROM` to `LEARNING_FROM + --window`: the learning phase, after the
first round. To get there in seconds rather than minutes each run's first round is brought to
step 2 000 (the PEBBLE family: 1 000 unsupervised steps; S-EPOA: 2 initial rollouts and a
5 000-step snapshot, pretrained untimed); the update, the acting and the reward per step are
the spec's. One CSV row per measurement goes to OUT/throughput.csv as it comes, with the mean
GPU utilisation over the measurement where `nvidia-smi` is there; rows already in the file are
skipped, so calls under a device time limit add up, and `--budget-seconds` starts no new
measurement after that much wall time.

`project` gives the whole grid's wall time at N runs at once: per task and variant, its runs'
steps over the aggregate rate measured at N (a pair not measured borrows the variant's rate on
a measured task, and says so), plus the APS snapshots' steps over `--pretrain-steps-per-s`.
Feedback rounds' reward training falls outside the timed window; their share is measured apart
(`gpu_check.sh sepoa`, benchmarks/README.md).
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from experiments.spec import Spec, load_spec  # noqa: E402

LEARNING_FROM = 3000
"""the timed window starts here, a thousand steps after the brought-forward first round"""
EARLY_FIRST_ROUND = {
    "pebble": ["unsup_steps=1000"], "surf": ["unsup_steps=1000"], "rune": ["unsup_steps=1000"],
    "rime": ["unsup_steps=1000"], "sac": [],
    "sepoa": ["skill.initial_rollouts=2", "skill.pretrain_steps=5000"],
}
"""per algorithm: what brings its first round to step 2 000 (SAC has none)"""
COLUMNS = ["task", "variant", "algo", "workers", "steps_per_s", "vs_one", "gpu_util",
           "seconds"]
ROW = re.compile(r"^\s*(\d+)\s+([\d.]+)\s+(\S+)\s+([\d.]+)")
"""bench_shared_device.py's line per N: workers, aggregate steps/s, ratio, launch steps/s"""


def counts(text: str) -> list[int]:
    values = [int(v) for v in text.split(",") if v.strip()]
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: give worker counts such as 1,4,8")
    return values


class GpuSampler:
    """The GPU's mean utilisation while it runs, from `nvidia-smi` twice a second (None where
    there is no NVIDIA GPU)."""

    def __init__(self) -> None:
        self.values: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def __enter__(self) -> GpuSampler:
        if shutil.which("nvidia-smi"):
            self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._stop.set()

    def _sample(self) -> None:
        while not self._stop.wait(0.5):
            out = subprocess.run(["nvidia-smi", "--query-gpu=utilization.gpu",
                                  "--format=csv,noheader,nounits"], capture_output=True,
                                 text=True).stdout.split()
            if out and out[0].isdigit():
                self.values.append(float(out[0]))

    @property
    def mean(self) -> float | None:
        return sum(self.values) / len(self.values) if self.values else None


def measure_one(spec: Spec, task: str, algo: str, n: int, args: argparse.Namespace) -> float:
    """The aggregate steps/s of n runs of `algo` on `task` sharing the device."""
    sets = [f"{k}={str(v).lower() if isinstance(v, bool) else v}"
            for k, v in spec.overrides.items()] + EARLY_FIRST_ROUND[algo]
    command = [sys.executable, str(ROOT / "benchmarks" / "bench_shared_device.py"),
               "--device", args.device, "--workers", str(n), "--task", task,
               "--preset", spec.preset, "--algo", algo, "--threads", str(args.threads),
               "--steps", str(args.from_step + args.window), "--from-step", str(args.from_step)]
    for item in sets:
        command += ["--set", item]
    # A session of its own: at a timeout the launcher's workers go with it, not on as orphans.
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=args.timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise RuntimeError(f"{task} {algo} x{n}: not done in {args.timeout} s") from None
    rows = [m for line in stdout.splitlines() if (m := ROW.match(line))]
    if proc.returncode != 0 or not rows:
        raise RuntimeError(f"{task} {algo} x{n}: exit {proc.returncode}\n"
                           f"{stdout[-1500:]}{stderr[-1500:]}")
    return float(rows[-1].group(2))


def measure(spec: Spec, args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = out / "throughput.csv"
    done = set()
    if table.exists():
        with open(table, newline="") as f:
            done = {(r["task"], r["variant"], int(r["workers"])) for r in csv.DictReader(f)}
    else:
        table.write_text(",".join(COLUMNS) + "\n")
    single = {}  # (task, variant) -> the rate of one run alone, for the ratio
    if table.exists():
        with open(table, newline="") as f:
            single = {(r["task"], r["variant"]): float(r["steps_per_s"])
                      for r in csv.DictReader(f) if r["workers"] == "1"}
    start, failed = time.perf_counter(), 0
    tasks = args.tasks or list(spec.tasks)
    variants = [v for v in spec.variants if not args.variants or v.label in args.variants]
    for task in tasks:
        for variant in variants:
            for n in args.workers:
                if (task, variant.label, n) in done:
                    continue
                if time.perf_counter() - start > args.budget_seconds:
                    print("budget spent: the rest is left for the next call", flush=True)
                    return 1 if failed else 0
                began = time.perf_counter()
                try:
                    with GpuSampler() as gpu:
                        rate = measure_one(spec, task, variant.algo, n, args)
                except RuntimeError as err:
                    print(f"failed: {err}", flush=True)
                    failed += 1
                    continue
                seconds = time.perf_counter() - began
                if n == 1:
                    single[(task, variant.label)] = rate
                alone = single.get((task, variant.label))
                ratio = f"{rate / alone:.2f}x" if alone else "-"
                util = "" if gpu.mean is None else f"{gpu.mean:.0f}"
                with open(table, "a", newline="") as f:
                    csv.writer(f).writerow([task, variant.label, variant.algo, n,
                                            f"{rate:.1f}", ratio, util, f"{seconds:.0f}"])
                print(f"{task} {variant.label} x{n}: {rate:.1f} steps/s ({ratio}), GPU "
                      f"{util or '-'} %, {seconds:.0f} s", flush=True)
    return 1 if failed else 0


def project(spec: Spec, args: argparse.Namespace) -> int:
    with open(args.measured, newline="") as f:
        rows = [r for r in csv.DictReader(f) if int(r["workers"]) == args.workers]
    if not rows:
        raise SystemExit(f"no measurement at {args.workers} workers in {args.measured}")
    rate = {(r["task"], r["variant"]): float(r["steps_per_s"]) for r in rows}
    runs: dict[tuple[str, str], int] = {}
    for run in spec.runs():
        runs[(run.task, run.variant)] = runs.get((run.task, run.variant), 0) + 1
    total, lines = 0.0, []
    for (task, variant), n in runs.items():
        measured = rate.get((task, variant))
        note = ""
        if measured is None:
            others = [(t, r) for (t, v), r in rate.items() if v == variant]
            if not others:
                raise SystemExit(f"{variant}: measured on no task at {args.workers} workers")
            note = f" (rate of {others[0][0]})"
            measured = others[0][1]
        hours = n * spec.steps / measured / 3600
        total += hours
        lines.append(f"  {task:<22} {variant:<8} {n:>3} runs  {measured:>8.1f} steps/s  "
                     f"{hours:>6.1f} h{note}")
    print(f"{spec.name}: {len(spec.runs())} runs of {spec.steps:,} steps, {args.workers} at "
          f"once, aggregate rates after the first round")
    print("\n".join(lines))
    pretrain_hours = 0.0
    snapshots = _snapshot_steps(spec)
    if snapshots and args.pretrain_steps_per_s:
        pretrain_hours = snapshots / args.pretrain_steps_per_s / 3600
        print(f"  APS snapshots: {snapshots:,} steps at {args.pretrain_steps_per_s:.0f} "
              f"steps/s: {pretrain_hours:.1f} h")
    elif snapshots:
        print(f"  APS snapshots: {snapshots:,} steps, not projected (no --pretrain-steps-per-s)")
    print(f"projected: {total + pretrain_hours:.1f} h (goal {args.goal_hours:g} h), feedback "
          "rounds' reward training not included")
    return 0


def _snapshot_steps(spec: Spec) -> int:
    """APS steps of the grid's snapshots: one per task, backend, length and seed."""
    seen = {}
    for run in spec.runs():
        cfg = run.config()
        if cfg.algo == "sepoa" and cfg.skill.pretrain_steps:
            seen[(cfg.task, cfg.skill.backend, cfg.skill.pretrain_steps, cfg.seed)] = (
                cfg.skill.pretrain_steps)
    return sum(seen.values())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="action", required=True)
    m = sub.add_parser("measure")
    m.add_argument("spec")
    m.add_argument("--out", required=True)
    m.add_argument("--device", default="cuda")
    m.add_argument("--workers", type=counts, default=[1, 4, 8])
    m.add_argument("--tasks", nargs="*", default=None)
    m.add_argument("--variants", nargs="*", default=None)
    m.add_argument("--threads", type=int, default=2)
    m.add_argument("--from-step", type=int, default=LEARNING_FROM,
                   help="the timed window's first step (after the first round)")
    m.add_argument("--window", type=int, default=2000, help="timed steps per run")
    m.add_argument("--timeout", type=int, default=300, help="seconds per measurement")
    m.add_argument("--budget-seconds", type=float, default=480)
    pr = sub.add_parser("project")
    pr.add_argument("spec")
    pr.add_argument("measured")
    pr.add_argument("--workers", type=int, default=8)
    pr.add_argument("--pretrain-steps-per-s", type=float, default=None)
    pr.add_argument("--goal-hours", type=float, default=48)
    args = p.parse_args(argv)
    spec = load_spec(args.spec)
    return measure(spec, args) if args.action == "measure" else project(spec, args)


if __name__ == "__main__":
    raise SystemExit(main())

"""Where a window of a run's steps spends its time, op by op: torch's profiler over N steps of a
real run, after its first round (the phase shares of run_profile.py say which phase is slow;
this says what in it, and on a GPU how busy the GPU was).

    .venv/bin/python benchmarks/profile_steps.py --preset small --algo pebble --from-step 2000
    python3 benchmarks/profile_steps.py --device cuda --preset paper --algo pebble \
        --from-step 10500 --steps 1000 --set sac.cuda_graph=true

The run trains from nothing in a temporary folder (scripted teacher, the preset's schedule; an
S-EPOA snapshot is pretrained first, untimed) until step `--from-step`, is profiled for
`--steps` steps, and stops at the end of that episode. Printed: the window's wall time per step;
on a GPU, the GPU's busy time (the kernels' own time, summed) as a share of the window's wall
time, which says whether the run waits on the GPU or the GPU on the run; the host time torch's
ops hold; then the ops that took the most time of their own, on the device and on the host; on
a GPU, last, how often the host waited for it and at which lines (torch's sync debug mode, whose
warning per wait adds a little to the window's time).
`--trace FILE` also writes the window as a Chrome trace (chrome://tracing, Perfetto).
`--pretraining` profiles a window of the skill pretraining (`skill.backend`, the preset's
widths) instead of an online run: the window should start after `skill.seed_steps`, where the
updates begin.

    python3 benchmarks/profile_steps.py --device cuda --preset paper --pretraining \
        --from-step 6000 --steps 1000 --set sac.cuda_graph=true
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import torch  # noqa: E402
from bench_run import overrides_of  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

from runvocab.config import build_config  # noqa: E402
from runvocab.snapshot_names import default_snapshot_path  # noqa: E402
from trainer.gpu_waits import GpuWaits  # noqa: E402
from trainer.hooks import RunHooks  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402
from trainer.skills.pretrain import PretrainingLeft, pretrain, pretrain_once  # noqa: E402


class ProfileWindow(RunHooks):
    """Profiles steps (start, start + steps], then asks the run to stop at its episode's end."""

    def __init__(self, start: int, steps: int, cuda: bool):
        self.start, self.end, self.cuda = start, start + steps, cuda
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        self.profiler = profile(activities=activities)
        self.syncs = GpuWaits() if cuda else None
        self.wall = 0.0
        self.began: float | None = None

    def stop_requested(self, step: int) -> bool:
        if step == self.start and self.began is None:
            if self.syncs is not None:
                torch.cuda.synchronize()
                self.syncs.start()
            self.profiler.start()
            self.began = time.perf_counter()
        elif step == self.end and self.began is not None and not self.wall:
            if self.syncs is not None:
                self.syncs.stop()
                torch.cuda.synchronize()
            self.wall = time.perf_counter() - self.began
            self.profiler.stop()
        return step >= self.end


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="dmc:cheetah_run")
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    p.add_argument("--algo", default="pebble")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--from-step", type=int, required=True,
                   help="the step the window starts at (after the first round, say)")
    p.add_argument("--steps", type=int, default=500, help="steps in the window")
    p.add_argument("--rows", type=int, default=15, help="ops listed per table")
    p.add_argument("--trace", help="also write the window as a Chrome trace to this file")
    p.add_argument("--pretraining", action="store_true",
                   help="profile the skill pretraining's steps, not an online run's")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other config field, e.g. sac.cuda_graph=true")
    args = p.parse_args()
    if args.from_step < 1 or args.steps < 1:
        raise SystemExit("error: --from-step and --steps take a whole number of steps, at least 1")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda, but torch finds no CUDA device")
    folder = tempfile.mkdtemp(prefix="profile-steps-")
    length = args.from_step + args.steps + 10_000
    overrides = {"algo": args.algo, "steps": length,
                 "device": args.device, "threads": args.threads, "run_dir": folder + "/run",
                 "skill.snapshot_dir": os.path.join(folder, "snapshots")}
    try:
        cfg = build_config(args.task, args.preset, overrides | overrides_of(args.set))
    except (ValueError, TypeError) as err:
        raise SystemExit(f"error: {err}") from None
    window = ProfileWindow(args.from_step, args.steps, args.device == "cuda")
    if args.pretraining:
        cfg = dataclasses.replace(cfg, skill=dataclasses.replace(cfg.skill, pretrain_steps=length))
        try:
            pretrain(cfg, out=default_snapshot_path(cfg), progress=False,
                     tick=window.stop_requested, quality_skills=0)
        except PretrainingLeft:
            pass  # the window asked it to stop: what is measured is done
        what = f"{cfg.skill.backend} pretraining"
    else:
        if args.algo == "sepoa" and cfg.skill.pretrain_steps > 0:
            pretrain_once(cfg, default_snapshot_path(cfg))
        TrainingRun(cfg, progress=False, hooks=window).train()
        what = args.algo
    if not window.wall:
        raise SystemExit(f"error: the run ended before step {window.end}")

    events = window.profiler.key_averages()
    print(f"{args.task} {what} ({args.preset}) on {args.device}, {args.threads} thread(s); "
          f"steps {window.start}-{window.end}: {window.wall / args.steps * 1e3:.2f} ms a step; "
          f"folder {folder}")
    if window.cuda:
        busy_us = sum(e.self_device_time_total for e in events)
        print(f"GPU busy {busy_us / 1e6:.2f} s of {window.wall:.2f} s "
              f"({busy_us / 1e6 / window.wall:.0%}; {busy_us / args.steps / 1e3:.2f} ms a step)")
        print(events.table(sort_by="self_device_time_total", row_limit=args.rows))
    if window.syncs is not None:
        lines = window.syncs.by_line()
        print(f"host waits for the GPU: {sum(lines.values())} in the window "
              f"({sum(lines.values()) / args.steps:.1f} a step), by line:")
        for where, count in lines.most_common(args.rows):
            print(f"  {count:8d}  {where}")
    host_s = sum(e.self_cpu_time_total for e in events) / 1e6
    print(f"torch ops on the host {host_s:.2f} s of {window.wall:.2f} s "
          f"({host_s / window.wall:.0%}); the rest is the environment, NumPy, Python and waiting")
    print(events.table(sort_by="self_cpu_time_total", row_limit=args.rows))
    if args.trace:
        window.profiler.export_chrome_trace(args.trace)
        print(f"trace: {args.trace}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Environment steps per second of whole runs: the eager SAC update against the update replayed
from CUDA graphs (`sac.cuda_graph`), the same run otherwise, sides alternated.

    .venv/bin/python benchmarks/bench_run.py --preset small --algo pebble --steps 12000
    python3 benchmarks/bench_run.py --device cuda --preset paper --algo sepoa --steps 30000 \
        --set skill.pretrain_steps=5000

Each side trains the run from nothing in a folder of its own (scripted teacher, rounds and
evaluations as configured; S-EPOA pretrains its snapshot once, shared by both sides, before
anything is timed). Printed per side: steps/s over the timed rows, and the phase profile
(benchmarks/run_profile.py), whose "updates" share is what the graphs shorten. On the CPU the
graph setting is ignored, so the sides should agree (a check of the benchmark itself).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from run_profile import profile  # noqa: E402

from runvocab.config import build_config, parse_value  # noqa: E402
from runvocab.snapshot_names import default_snapshot_path  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402
from trainer.phase_clock import PHASES  # noqa: E402
from trainer.skills.pretrain import pretrain_once  # noqa: E402


def overrides_of(pairs: list[str]) -> dict[str, object]:
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise SystemExit(f"error: --set takes KEY=VALUE, got {pair!r}")
        try:
            out[key] = parse_value(key, value)
        except (ValueError, KeyError) as err:
            raise SystemExit(f"error: --set {pair}: {err}") from None
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="dmc:cheetah_run")
    p.add_argument("--preset", default="small", choices=("paper", "small", "tiny"))
    p.add_argument("--algo", default="pebble")
    p.add_argument("--steps", type=int, default=12_000)
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=1, help="runs per side, alternated")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other config field, e.g. skill.pretrain_steps=5000")
    p.add_argument("--from-step", type=int, default=0,
                   help="profile only episodes ending after this step (e.g. after round 0)")
    p.add_argument("--sides", default="eager,graphed",
                   help="which sides run: eager,graphed (the ratio) or one of them (a GPU "
                        "host's minutes are few)")
    args = p.parse_args()
    sides = args.sides.split(",")
    if not sides or any(side not in ("eager", "graphed") for side in sides) \
            or len(set(sides)) != len(sides):
        raise SystemExit(f"error: --sides {args.sides}: takes eager, graphed or eager,graphed")
    folder = tempfile.mkdtemp(prefix="bench-run-")
    base = {"algo": args.algo, "steps": args.steps, "device": args.device,
            "threads": args.threads, "skill.snapshot_dir": os.path.join(folder, "snapshots")}
    base |= overrides_of(args.set)
    try:
        cfg = build_config(args.task, args.preset, base)
    except (ValueError, TypeError) as err:
        raise SystemExit(f"error: {err}") from None
    if args.algo == "sepoa" and cfg.skill.pretrain_steps > 0:
        pretrain_once(cfg, default_snapshot_path(cfg))  # shared by both sides, not timed
    rates: dict[str, list[float]] = {side: [] for side in sides}
    # Evaluation is 10 episodes every eval_every steps: a short window holds one or none, so
    # the rate without it is printed too (a whole run's cost adds its evaluations back).
    training: dict[str, list[float]] = {side: [] for side in sides}
    profiles: dict[str, dict[str, float]] = {}
    for r in range(args.repeats):
        for side in (sides if r % 2 == 0 else sides[::-1]):
            run_dir = os.path.join(folder, f"{side}-{r}")
            side_cfg = build_config(args.task, args.preset, base | {
                "run_dir": run_dir, "sac.cuda_graph": side == "graphed"})
            TrainingRun(side_cfg, progress=False).train()
            steps, seconds = profile(run_dir, args.from_step)
            rates[side].append(steps / seconds["total"])
            training[side].append(steps / (seconds["total"] - seconds["evaluation"]))
            profiles[side] = seconds
    print(f"{args.task} {args.algo} ({args.preset}), {args.steps} steps on {args.device}, "
          f"{args.threads} thread(s), {args.repeats} run(s) per side; folder {folder}")
    for side, values in rates.items():
        total = profiles[side]["total"]
        shares = "  ".join(f"{phase} {profiles[side][phase] / total:.0%}"
                           for phase in (*PHASES, "other") if profiles[side][phase] > 0)
        print(f"{side:8s} {statistics.median(values):8.1f} steps/s "
              f"({statistics.median(training[side]):.1f} without evaluation)   {shares}")
    if len(rates) == 2:
        ratio = statistics.median(rates["graphed"]) / statistics.median(rates["eager"])
        print(f"graphed / eager: {ratio:.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

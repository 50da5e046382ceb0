"""Distinguishability of selected queries: disagreement against S-EPOA's skill-based rule.

The paper's table metric: the fraction of selected queries the noisy teacher (eps) can tell
apart, |R(tau0) - R(tau1)| >= eps * |R_avg| over the two segments' whole trajectories. An S-EPOA
run trains as usual (its skill rule picks the queries that are answered) with
`feedback.compare_rule disagreement`: at every round the disagreement rule is also applied to
the same agent, pool and reward model (a random stream and a teacher copy of its own, so the
run is not disturbed), and rounds.csv records both ratios. The first round is uniform for both
rules, so it is left out. Averages are over rounds, then over seeds.

    .venv/bin/python -m experiments.diagnostics.distinguishability --task dmc:cheetah_run \\
        --eps 0.3 --preset small --seeds 0 1 --steps 50000 --snapshot snapshots/<...>.pt

The paper reports 0.327 (disagreement) against 0.484 (skill-based) at eps = 0.3 on cheetah_run.
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo's import

from runvocab.config import build_config  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402


def one_seed(task: str, preset: str, eps: float, seed: int, steps: int, snapshot: str,
             overrides: dict) -> list[tuple[int, float, float]]:
    """(round, disagreement's ratio, the skill rule's ratio) for each round after the first."""
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = build_config(task, preset, {
            "algo": "sepoa", "seed": seed, "steps": steps, "teacher.eps": eps, "threads": 1,
            "eval_every": 0, "skill.snapshot": snapshot, "run_dir": run_dir,
            "feedback.compare_rule": "disagreement"} | overrides)
        TrainingRun(cfg, progress=False).train()
        with open(os.path.join(run_dir, "rounds.csv"), newline="") as f:
            rounds = list(csv.DictReader(f))
    return [(int(r["round"]), float(r["compare_distinguishable_ratio"]),
             float(r["distinguishable_ratio"])) for r in rounds[1:]]


def _spread(xs: list[float]) -> str:
    return f" ± {statistics.stdev(xs):.3f}" if len(xs) > 1 else ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="dmc:cheetah_run")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--eps", type=float, default=0.3)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=50_000)
    parser.add_argument("--snapshot", required=True, help="the pretraining snapshot (sepoa "
                        "pretrain); its length is the pretraining length reported")
    parser.add_argument("--feedback-every", type=int, default=0,
                        help="steps between rounds; 0 = the preset's")
    parser.add_argument("--jobs", type=int, default=2, help="seeds run in parallel")
    args = parser.parse_args()
    overrides = {"feedback.every": args.feedback_every} if args.feedback_every else {}

    start = time.time()
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = {seed: pool.submit(one_seed, args.task, args.preset, args.eps, seed,
                                     args.steps, args.snapshot, overrides) for seed in args.seeds}
        results = {seed: f.result() for seed, f in futures.items()}

    print(f"{args.task}, preset {args.preset}, eps {args.eps}, {args.steps} steps per seed, "
          f"snapshot {os.path.basename(args.snapshot)} ({time.time() - start:.0f} s)")
    print("seed  round  disagreement  skill-based")
    per_seed = []
    for seed, rows in results.items():
        for rnd, dis, skill in rows:
            print(f"{seed:4d}  {rnd:5d}  {dis:12.3f}  {skill:11.3f}")
        if rows:
            per_seed.append((np.mean([r[1] for r in rows]), np.mean([r[2] for r in rows])))
    dis_means = [float(d) for d, _ in per_seed]
    skill_means = [float(s) for _, s in per_seed]
    print(f"mean over rounds and seeds: disagreement {np.mean(dis_means):.3f}"
          f"{_spread(dis_means)}, skill-based {np.mean(skill_means):.3f}{_spread(skill_means)} "
          f"(paper, cheetah_run eps 0.3: 0.327 vs 0.484)")


if __name__ == "__main__":
    main()

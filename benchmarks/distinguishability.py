"""Distinguishability of selected queries: disagreement against S-EPOA's skill-based rule.

The paper's table metric: the fraction of selected queries the noisy teacher (eps) can tell
apart, |R(tau0) - R(tau1)| >= eps * |R_avg| over the two segments' whole trajectories. An S-EPOA
run trains as usual (its skill rule picks the queries that are answered); at every round the
disagreement rule is also applied to the same pretrained agent, the same trajectory pool and
the same reward model (with a random stream of its own, so the run is not disturbed), and both
selections are scored with the teacher's threshold at that moment. The first round is uniform
for both rules, so it is left out. Averages are over rounds, then over seeds.

    .venv/bin/python benchmarks/distinguishability.py --task dmc:cheetah_run --eps 0.3 \\
        --preset small --seeds 0 1 --steps 50000 --snapshot snapshots/<...>.pt

The paper reports 0.327 (disagreement) against 0.484 (skill-based) at eps = 0.3 on cheetah_run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
os.environ.setdefault("MUJOCO_GL", "egl")

from trainer.config import build_config  # noqa: E402
from trainer.feedback import Query  # noqa: E402
from trainer.hooks import RunHooks  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402
from trainer.query_selection import select_queries  # noqa: E402
from trainer.trajectories import TrajectoryPool  # noqa: E402


class CompareRules(RunHooks):
    """At each round, the distinguishable fraction of the skill rule's queries (those asked)
    and of the disagreement rule's picks on the same pool and reward model."""

    def __init__(self, eps: float, seed: int):
        self.eps, self.seed = eps, seed
        self.run: TrainingRun | None = None
        self.rows: list[tuple[int, float, float]] = []

    def round_opened(self, queries: list[Query], pool: TrajectoryPool) -> None:
        run = self.run
        assert run is not None and run.feedback is not None
        fb, cfg = run.feedback, run.cfg.feedback
        if queries[0].rule == "uniform":
            return
        threshold = self.eps * abs(float(np.mean(pool.returns[-run.cfg.teacher.
                                                              recent_trajectories:])))
        trajectories = list(pool.trajectories)
        rng = np.random.default_rng([self.seed, fb.rounds])
        other = select_queries("disagreement", fb.model, trajectories, len(queries),
                               len(queries) * cfg.candidate_factor, cfg.segment_length, rng)
        returns = np.array([t.true_return for t in trajectories])
        gap = np.abs(returns[other.queries.traj0] - returns[other.queries.traj1])
        disagreement = float(np.mean(gap >= threshold))
        skill = float(np.mean([q.distinguishable for q in queries]))
        self.rows.append((fb.rounds, disagreement, skill))


def one_seed(task: str, preset: str, eps: float, seed: int, steps: int, snapshot: str,
             overrides: dict) -> list[tuple[int, float, float]]:
    hooks = CompareRules(eps, seed)
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = build_config(task, preset, {
            "algo": "sepoa", "seed": seed, "steps": steps, "teacher.eps": eps, "threads": 1,
            "eval_every": 0, "skill.snapshot": snapshot, "run_dir": run_dir} | overrides)
        run = TrainingRun(cfg, progress=False, hooks=hooks)
        hooks.run = run
        run.train()
    return hooks.rows


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
    parser.add_argument("--jobs", type=int, default=2, help="seeds run in parallel")
    args = parser.parse_args()

    start = time.time()
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = {seed: pool.submit(one_seed, args.task, args.preset, args.eps, seed,
                                     args.steps, args.snapshot, {}) for seed in args.seeds}
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
    dis = [d for d, _ in per_seed]
    skill = [s for _, s in per_seed]
    print(f"mean over rounds and seeds: disagreement {np.mean(dis):.3f}{_spread(dis)}, "
          f"skill-based {np.mean(skill):.3f}{_spread(skill)} (paper, cheetah_run eps 0.3: "
          f"0.327 vs 0.484)")


if __name__ == "__main__":
    main()

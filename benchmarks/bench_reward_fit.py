"""Offline reward fitting against the run's own reward model, at the `small` preset.

A scripted run is trained through the queue by an in-process worker (its labels are given
through the same queue operations a person's take), exported as a Minari dataset
(`rundata.dataset.write_dataset`), and fitted offline (`trainer.reward_fit.fit`) with several
held-out splits, round by round as the run trained (`--schedule rounds`) or once on all pairs.
For each split it prints the fit's held-out accuracy on labelled pairs, the run's own final
reward model's accuracy on the same pairs (which it trained on, as on every label of the run),
both models' accuracy on random segment pairs ordered by their true returns (pairs neither
trained on: with the ideal teacher, eps 0, exactly the labels it would give), and both models'
correlation of r_hat with the true reward over the exported episodes.

    .venv/bin/python benchmarks/bench_reward_fit.py --keep /tmp/fit-run   # cheetah, 30 k steps
    .venv/bin/python benchmarks/bench_reward_fit.py --reuse /tmp/fit-run --schedule once
    .venv/bin/python benchmarks/bench_reward_fit.py --steps 60000 --budget 600 --eps 0.3

Exits 1 when the fit's mean accuracy on the true-order pairs is more than `--tolerance` below
the run's own model's.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

import numpy as np
import torch

from labelqueue import create_run, make_engine, migrate, session_factory
from rundata.dataset import read_dataset, write_dataset
from trainer.clips import ClipConfig
from trainer.reward_fit import compare, fit, run_reward_model
from trainer.worker import WorkerConfig, run_worker


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="dmc:cheetah_run")
    p.add_argument("--preset", default="small")
    p.add_argument("--algo", default="pebble")
    p.add_argument("--steps", type=int, default=30_000)
    p.add_argument("--budget", type=int, default=300)
    p.add_argument("--per-round", type=int, default=60)
    p.add_argument("--eps", type=float, default=0.0, help="the scripted teacher's eps")
    p.add_argument("--update-every", type=int, default=4,
                   help="a SAC update every this many steps (the run's speed)")
    p.add_argument("--splits", type=int, default=3, help="held-out splits (seeds) to fit")
    p.add_argument("--holdout", type=float, default=0.2)
    p.add_argument("--tolerance", type=float, default=0.05)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--schedule", choices=("rounds", "once"), default="rounds")
    p.add_argument("--keep", default=None, help="keep the run and its export in this folder")
    p.add_argument("--reuse", default=None, help="fit a run kept with --keep again")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    print(f"load average {os.getloadavg()[0]:.2f}; torch threads {args.threads}")

    with tempfile.TemporaryDirectory(prefix="bench-reward-fit-") as tmp_dir:
        tmp = Path(args.reuse or args.keep or tmp_dir)
        if args.reuse:
            return fits(args, tmp)
        tmp.mkdir(parents=True, exist_ok=True)
        url = f"sqlite:///{tmp / 'queue.db'}"
        migrate(url)
        sessions = session_factory(make_engine(url))
        with sessions() as session:
            run = create_run(
                session, name="bench", task=args.task, algo=args.algo, preset=args.preset,
                seed=0, budget=args.budget, teacher="scripted",
                teacher_params={"eps": args.eps},
                config={"steps": args.steps, "threads": args.threads,
                        "update_every": args.update_every,
                        "feedback.per_round": args.per_round})
            run_id = run.id
        start = time.perf_counter()
        run_worker(WorkerConfig(database_url=url, data_dir=tmp / "data", once=True,
                                poll_seconds=0.1, clip=ClipConfig(width=64, height=64)))
        trained = time.perf_counter() - start
        with sessions() as session:
            summary = write_dataset(session, run_id=run_id, clips_root=tmp / "data" / "clips",
                                    root=tmp / "datasets", dataset_id="bench/run-v0")
        print(f"run: {args.task} {args.algo} {args.preset}, {args.steps} steps, eps "
              f"{args.eps}, trained in {trained:.0f} s; export: {summary.episodes} episodes, "
              f"{summary.labels} labels")
        return fits(args, tmp)


def fits(args: argparse.Namespace, tmp: Path) -> int:
    dataset = read_dataset(str(tmp / "datasets" / "bench" / "run-v0"))
    run_model = run_reward_model(str(tmp / "data" / "runs" / "run-1" / "checkpoint.pt"),
                                 dataset)
    print(f"schedule {args.schedule}, held-out share {args.holdout}")
    rows = []
    print(f"{'split':>5} {'held':>5} {'fit held':>9} {'run held':>9} {'fit true':>9} "
          f"{'run true':>9} {'fit r':>7} {'run r':>7} {'epochs':>6} {'fit s':>6}")
    for seed in range(args.splits):
        result = fit(dataset, holdout=args.holdout, seed=seed, schedule=args.schedule)
        m = result.metrics | compare(run_model, result, dataset, seed)
        rows.append(m)
        print(f"{seed:>5} {int(m['heldout_pairs']):>5} {m['heldout_accuracy']:>9.3f} "
              f"{m['run_heldout_accuracy']:>9.3f} {m['true_order_accuracy']:>9.3f} "
              f"{m['run_true_order_accuracy']:>9.3f} {m['reward_corr']:>7.3f} "
              f"{m['run_reward_corr']:>7.3f} {int(m['epochs']):>6} {m['seconds']:>6.1f}")
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    gap = mean["run_true_order_accuracy"] - mean["true_order_accuracy"]
    print(f"mean held-out accuracy: fit {mean['heldout_accuracy']:.3f}, run's own "
          f"{mean['run_heldout_accuracy']:.3f} (trained on them); true-order accuracy: fit "
          f"{mean['true_order_accuracy']:.3f}, run's own {mean['run_true_order_accuracy']:.3f} "
          f"(gap {gap:+.3f}, tolerance {args.tolerance}); r_hat vs true reward: fit "
          f"{mean['reward_corr']:.3f}, run's own {mean['run_reward_corr']:.3f}")
    return 1 if gap > args.tolerance else 0


if __name__ == "__main__":
    sys.exit(main())

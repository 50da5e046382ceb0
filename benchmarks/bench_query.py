"""Query scoring: `select_queries("disagreement", ...)` end to end on a PEBBLE-sized round.

100 trajectories of 1000 steps (cheetah dims, random data), the default 3-member reward ensemble
and 10 000 candidate pairs of 50-step segments, of which the top 1000 are kept. The peer is the
naive way: each candidate's 2 x 50 transitions scored separately through the ensemble (1 M
transition evaluations instead of the pool's 100 k), batched, then the same statistics.

    .venv/bin/python benchmarks/bench_query.py
    .venv/bin/python benchmarks/bench_query.py --bf16     # also time bf16 autocast, with overlap
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np
import torch

from runvocab.config import RewardConfig
from trainer.query_selection import (
    SCORING_CHUNK,
    Candidates,
    disagreement,
    preference_probabilities,
    sample_candidates,
    select_queries,
    top_k,
)
from trainer.reward_model import RewardModel
from trainer.trajectories import Trajectory

OBS_DIM, ACTION_DIM = 17, 6


def make_pool(n: int, length: int, seed: int) -> list[Trajectory]:
    rng = np.random.default_rng(seed)
    return [
        Trajectory(
            id=i,
            obs=rng.normal(size=(length, OBS_DIM)).astype(np.float32),
            actions=rng.uniform(-1, 1, (length, ACTION_DIM)).astype(np.float32),
            true_rewards=rng.random(length).astype(np.float32),
            states=np.zeros((length, 1)),
            context=0,
            success=False,
        )
        for i in range(n)
    ]


def naive_select(model: RewardModel, pool: list[Trajectory], n_queries: int, n_candidates: int,
                 segment_length: int, rng: np.random.Generator, chunk: int = 1000) -> Candidates:
    """Gather every segment's transitions and score them all: 2 * H per candidate."""
    lengths = np.array([t.length for t in pool])
    cands = sample_candidates(lengths, n_candidates, segment_length, rng)
    inputs = [np.concatenate([t.obs, t.actions], axis=1) for t in pool]
    steps = np.arange(segment_length)

    def returns(traj: np.ndarray, start: np.ndarray) -> torch.Tensor:
        out = []
        for i in range(0, len(traj), chunk):
            segs = np.stack([inputs[t][s + steps] for t, s in zip(traj[i : i + chunk],
                                                                   start[i : i + chunk],
                                                                   strict=True)])
            x = torch.from_numpy(segs.reshape(-1, segs.shape[-1]))
            # The same forward-pass chunk as ours, so only the amount of work differs.
            r = model.member_rewards(x, chunk=SCORING_CHUNK)
            out.append(r.reshape(-1, len(segs), segment_length).sum(-1))
        return torch.cat(out, dim=1)

    p = preference_probabilities(returns(cands.traj0, cands.start0),
                                 returns(cands.traj1, cands.start1))
    return cands.take(top_k(disagreement(p), n_queries))


def pairs(c: Candidates) -> set[tuple[int, int, int, int]]:
    return set(zip(c.traj0.tolist(), c.start0.tolist(), c.traj1.tolist(), c.start1.tolist(),
                   strict=True))


def timed(fn, repeats: int):
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--trajectories", type=int, default=100)
    p.add_argument("--length", type=int, default=1000, help="steps per trajectory")
    p.add_argument("--candidates", type=int, default=10_000)
    p.add_argument("--queries", type=int, default=1000)
    p.add_argument("--segment", type=int, default=50, help="segment length")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats (median)")
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--bf16", action="store_true",
                   help="also time bf16 autocast and report top-k overlap with fp32")
    p.add_argument("--skip-naive", action="store_true", help="skip the slow naive peer")
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    pool = make_pool(args.trajectories, args.length, seed=0)
    torch.manual_seed(0)  # the ensemble's initial weights
    model = RewardModel(OBS_DIM, ACTION_DIM, RewardConfig(), torch.device("cpu"), seed=0)

    def ours():
        return select_queries("disagreement", model, pool, args.queries,
                              args.candidates // args.queries,
                              args.segment, np.random.default_rng(1))

    ours()  # warm-up
    t_ours, sel = timed(ours, args.repeats)
    chosen = pairs(sel.queries)

    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average "
          f"{os.getloadavg()[0]:.2f}; pool {args.trajectories} x {args.length} steps, "
          f"{args.candidates} candidates of {args.segment} steps, top {args.queries}")
    print(f"{'method':<34} {'transitions':>12} {'seconds':>8} {'vs ours':>8}")
    pool_steps = args.trajectories * args.length
    print(f"{'ours (pool once, prefix sums)':<34} {pool_steps:>12} {t_ours:>8.3f} {1:>7.2f}x")

    if args.bf16:
        def ours_bf16():
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return ours()

        ours_bf16()
        t_bf16, sel16 = timed(ours_bf16, args.repeats)
        overlap = len(chosen & pairs(sel16.queries)) / len(chosen)
        print(f"{'ours, bf16 autocast':<34} {pool_steps:>12} {t_bf16:>8.3f} "
              f"{t_bf16 / t_ours:>7.2f}x   top-{args.queries} overlap with fp32 {overlap:.1%}")

    if not args.skip_naive:
        naive_steps = 2 * args.segment * args.candidates
        t_naive, naive = timed(lambda: naive_select(model, pool, args.queries, args.candidates,
                                                    args.segment, np.random.default_rng(1)),
                               max(1, args.repeats // 2))
        # Same rng seed, so the same candidates: the choice should match ours up to float ties.
        overlap = len(chosen & pairs(naive)) / len(chosen)
        print(f"{'naive (every segment separately)':<34} {naive_steps:>12} {t_naive:>8.3f} "
              f"{t_naive / t_ours:>7.2f}x   top-{args.queries} overlap with ours {overlap:.1%}")
    print(f"target: ours <= 1.5 s -> {'met' if t_ours <= 1.5 else 'missed'}")


if __name__ == "__main__":
    main()

"""The no-ground check over many clips: for each task, clips of `--length` steps cut from
random-action episodes and moved along the run by distances spread from `--behind` m behind the
start to `--ahead` m ahead (as far as a long-running agent gets; DMC's floors end 2 m behind
the start and 50-250 m ahead; fish's 1 m tank floor stays put and the fish is moved within it),
rendered with and without `ClipConfig.motion_cues`. Per task it
prints how many frames show no ground (less than `GROUND_MIN_FRACTION` of their pixels on a
floor, by MuJoCo's segmentation render of the clip's scene), the smallest share of ground in any
frame, the most sky in the lowest quarter of any frame (none: ground fills the lower part), the
body's height as a share of the frame's (median and 10th-90th percentiles: a random-action
body spends most of its clips fallen, lower than standing), and the frames checked per second.

    .venv/bin/python benchmarks/bench_ground.py                     # cheetah, walker, hopper,
                                                                    # quadruped, 40 clips each
    .venv/bin/python benchmarks/bench_ground.py --clips 200 --task dmc:cheetah_run
    .venv/bin/python benchmarks/bench_ground.py --all-following      # every following camera

Exits 1 when a frame with the cues has no ground.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

import numpy as np

from trainer.clips import (
    CLIP_CAMERAS,
    GROUND_MIN_FRACTION,
    ClipConfig,
    frame_shares,
    moved_states,
)
from trainer.envs import make_env

DEFAULT_TASKS = ["dmc:cheetah_run", "dmc:walker_run", "dmc:hopper_hop", "dmc:quadruped_run"]
FOLLOWING = {"cheetah": "dmc:cheetah_run", "walker": "dmc:walker_run",
             "hopper": "dmc:hopper_hop", "quadruped": "dmc:quadruped_run",
             "humanoid": "dmc:humanoid_run", "humanoid_CMU": "dmc:humanoid_CMU_run",
             "dog": "dmc:dog_run", "fish": "dmc:fish_swim", "swimmer": "dmc:swimmer_swimmer6"}
TANKS = {"dmc:fish_swim": 0.3}
"""tasks whose body stays over a small floor that is not moved (fish's 1 m tank): moved at
most this far (m), as the body can go"""


def episode_states(env, steps: int, rng: np.random.Generator) -> np.ndarray:
    env.reset()
    states = []
    for _ in range(steps):
        states.append(env.physics_state())
        env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
    return np.array(states)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", action="append", help="a DMC task (repeatable)")
    p.add_argument("--all-following", action="store_true",
                   help="one task of every domain whose clip camera follows the body")
    p.add_argument("--clips", type=int, default=40, help="clips per task")
    p.add_argument("--length", type=int, default=50, help="steps per clip")
    p.add_argument("--size", type=int, default=128, help="square frame side in pixels")
    p.add_argument("--behind", type=float, default=100.0)
    p.add_argument("--ahead", type=float, default=1500.0)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    assert set(FOLLOWING) == set(CLIP_CAMERAS)
    tasks = (list(FOLLOWING.values()) if args.all_following else args.task or DEFAULT_TASKS)
    cfg = ClipConfig(width=args.size, height=args.size)
    settings = {"with cues": cfg, "without": dataclasses.replace(cfg, motion_cues=False)}
    rng = np.random.default_rng(args.seed)

    print(f"{args.clips} clips of {args.length} frames per task at {args.size}x{args.size}, "
          f"moved {-args.behind:g} to +{args.ahead:g} m along the run; no ground: < "
          f"{GROUND_MIN_FRACTION:.0%} of a frame on a floor (MUJOCO_GL={os.environ['MUJOCO_GL']})")
    print(f"{'task':<24} {'setting':<10} {'frames':>7} {'no ground':>9} {'clips hit':>9} "
          f"{'min share':>9} {'median':>7} {'sky low':>7} {'body h [p10-p90]':>17} "
          f"{'frames/s':>8}")
    failed = False
    for task in tasks:
        with make_env(task, args.seed) as env:
            states = episode_states(env, args.length * 4, rng)
            low, high = ((-TANKS[task], TANKS[task]) if task in TANKS
                         else (-args.behind, args.ahead))
            cuts = [(int(rng.integers(0, len(states) - args.length + 1)),
                     float(rng.uniform(low, high)), float(rng.uniform(low, high)))
                    for _ in range(args.clips)]
            for name, setting in settings.items():
                clips, hit = [], 0
                t0 = time.perf_counter()
                for start, dx, dy in cuts:
                    moved = moved_states(env, states, dx, dy)
                    shares = frame_shares(env, moved, 0, start, args.length, setting)
                    clips.append(shares)
                    hit += bool((shares["ground"] < GROUND_MIN_FRACTION).any())
                seconds = time.perf_counter() - t0
                all_f, sky, body = (np.concatenate([c[k] for c in clips])
                                    for k in ("ground", "sky_below", "body_height"))
                bad = int((all_f < GROUND_MIN_FRACTION).sum())
                failed |= name == "with cues" and bad > 0
                p10, p50, p90 = np.percentile(body, [10, 50, 90])
                print(f"{task:<24} {name:<10} {len(all_f):>7} {bad:>9} {hit:>9} "
                      f"{all_f.min():>9.3f} {np.median(all_f):>7.3f} {sky.max():>7.3f} "
                      f"{f'{p50:.2f} [{p10:.2f}-{p90:.2f}]':>17} "
                      f"{len(all_f) / seconds:>8.0f}")
    print("verdict:", "a frame with the cues has no ground" if failed
          else "every frame with the cues shows the ground")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

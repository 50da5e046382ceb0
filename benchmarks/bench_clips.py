"""Query clips: seconds to render and encode one pair of segments, at the model's own render
quality against the fast settings (512-texel shadow map, no multisampling) and against
`ClipConfig`'s defaults (those, and 12 x 8 facets on built-in spheres and capsules).

A pair is what a labeller sees per query: two segments of `--length` steps re-rendered from
stored physics states at `--size` px and encoded as two h264 mp4 files. Per pair the script times
`render_segment` on both sides (render fps), `encode_mp4` of those frames (encode time), and
`render_query_clips`, which streams frames into ffmpeg while it renders (the pair total, the
figure the app pays). Each setting renders on an env of its own; sides alternate per pair.

    .venv/bin/python benchmarks/bench_clips.py                          # dmc:cheetah_run
    .venv/bin/python benchmarks/bench_clips.py --task dmc:quadruped_walk
    .venv/bin/python benchmarks/bench_clips.py --task metaworld:door-open
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

import numpy as np

from trainer.clips import ClipConfig, encode_mp4, render_query_clips, render_segment
from trainer.envs import make_env
from trainer.trajectories import Trajectory

TARGET_S = 1.0  # per pair, on 2 CPU cores


def record(task: str, steps: int, seed: int) -> Trajectory:
    """A random-action trajectory with the physics state of every step."""
    env = make_env(task, seed)
    rng = np.random.default_rng(seed)
    env.reset()
    states = []
    for _ in range(steps):
        states.append(env.physics_state())
        env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
    traj = Trajectory(id=0, obs=np.zeros((steps, 0), np.float32),
                      actions=np.zeros((steps, 0), np.float32),
                      true_rewards=np.zeros(steps, np.float32), states=np.array(states),
                      context=env.episode_context(), success=False)
    env.close()
    return traj


def cpu_ticks() -> tuple[int, int]:
    """(all, stolen) CPU ticks since boot; a VM's host can take time from it (Linux only)."""
    try:
        with open("/proc/stat") as f:
            ticks = [int(x) for x in f.readline().split()[1:]]
    except OSError:
        return 0, 0
    return sum(ticks[:8]), ticks[7]


def time_pair(env, traj: Trajectory, starts: tuple[int, int], length: int, out: Path,
              cfg: ClipConfig) -> dict[str, float]:
    t0 = time.perf_counter()
    frames = [render_segment(env, traj.states, traj.context, s, length, cfg) for s in starts]
    t1 = time.perf_counter()
    for side, f in enumerate(frames):
        encode_mp4(f, out / f"split-{side}.mp4", cfg)
    t2 = time.perf_counter()
    names = render_query_clips(env, traj, starts[0], traj, starts[1], length, out, "pair", cfg)
    t3 = time.perf_counter()
    return {"fps": 2 * length / (t1 - t0), "encode": t2 - t1, "pair": t3 - t2,
            "kb": sum((out / n).stat().st_size for n in names) / 2 / 1024}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="dmc:cheetah_run",
                   help="dmc:<domain>_<task> | metaworld:<name>")
    p.add_argument("--size", type=int, default=128, help="clip width and height in pixels")
    p.add_argument("--length", type=int, default=50, help="steps per segment")
    p.add_argument("--pairs", type=int, default=5, help="timed pairs per setting (median)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    size = {"width": args.size, "height": args.size}
    settings = {
        "model's own quality": ClipConfig(**size, shadow_size=None, multisamples=None,
                                          slices=None, stacks=None),
        "shadow 512, no MSAA": ClipConfig(**size, slices=None, stacks=None),
        "+ 12 x 8 facets (default)": ClipConfig(**size),
    }
    traj = record(args.task, args.length * (args.pairs + 2), args.seed)
    envs = {name: make_env(args.task, args.seed + 1) for name in settings}
    results: dict[str, list[dict[str, float]]] = {name: [] for name in settings}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for name, cfg in settings.items():  # warm-up: GL contexts, shaders, ffmpeg's first start
            time_pair(envs[name], traj, (0, args.length), args.length, out, cfg)
        ticks0 = cpu_ticks()
        for k in range(args.pairs):
            starts = (k * args.length // 2, (k + 2) * args.length // 2)
            # Alternate who goes first so drift (other load) hits both alike.
            for name in list(settings)[:: 1 if k % 2 == 0 else -1]:
                results[name].append(time_pair(envs[name], traj, starts, args.length, out,
                                               settings[name]))
        ticks1 = cpu_ticks()
    steal = (ticks1[1] - ticks0[1]) / max(1, ticks1[0] - ticks0[0])

    med = {name: {key: statistics.median(r[key] for r in rs) for key in rs[0]}
           for name, rs in results.items()}
    print(f"{args.task}: {args.pairs} pairs of 2 x {args.length} frames at {args.size}x"
          f"{args.size}, MUJOCO_GL={os.environ['MUJOCO_GL']}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}, CPU time stolen by the host {steal:.0%}")
    print(f"{'settings':<27} {'render fps':>10} {'encode s/pair':>13} {'pair s':>7} "
          f"{'kB/clip':>7}")
    for name, m in med.items():
        print(f"{name:<27} {m['fps']:>10.1f} {m['encode']:>13.3f} {m['pair']:>7.3f} "
              f"{m['kb']:>7.1f}")
    own, fast, default = med.values()
    for name, m in (("shadow 512, no MSAA", fast), ("default", default)):
        print(f"ratio {name} / own: render fps {m['fps'] / own['fps']:.2f}x, "
              f"pair time {m['pair'] / own['pair']:.2f}x")
    verdict = "met" if default["pair"] <= TARGET_S else "missed"
    print(f"target: default pair <= {TARGET_S:.1f} s -> {verdict}")
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main()

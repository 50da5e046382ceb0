"""Query clips: seconds to render and encode one pair of segments, at the model's own render
quality against the fast settings (512-texel shadow map, no multisampling), those with 12 x 8
facets on built-in spheres and capsules, and `ClipConfig`'s defaults (those, without the floor's
mirror image).

A pair is what a labeller sees per query: two segments of `--length` steps re-rendered from
stored physics states at `--size` px and encoded as two h264 mp4 files. Per pair the script times
`render_segment` on both sides (render fps), `encode_mp4` of those frames (encode time), and
`render_query_clips`, which streams frames into ffmpeg while it renders (the pair total, the
figure the app pays). Each setting renders on an env of its own; sides alternate per pair.

    .venv/bin/python benchmarks/bench_clips.py                          # dmc:cheetah_run
    .venv/bin/python benchmarks/bench_clips.py --task dmc:quadruped_walk
    .venv/bin/python benchmarks/bench_clips.py --task metaworld:door-open
    .venv/bin/python benchmarks/bench_clips.py --size 320x240             # one size (256x256)
    .venv/bin/python benchmarks/bench_clips.py --sizes                    # every run clip size

`--sizes` times only `ClipConfig`'s defaults, at each size a run may choose
(`runvocab.clip_format.CLIP_SIZES`), alternating the sizes per pair.

"pair s" is wall-clock time; "CPU s" the CPU time the pair cost this process and its ffmpeg
children. On a host busy with other work the first grows with the load and the second does
not: on an idle 2-core host the pair takes at most about its CPU time (render and encode
overlap).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

import numpy as np

from runvocab.clip_format import CLIP_SIZES, DEFAULT_CLIP_SIZE
from trainer.clips import ClipConfig, encode_mp4, render_query_clips, render_segment
from trainer.envs import make_env
from trainer.trajectories import Trajectory

TARGET_S = 1.0  # per pair, on 2 CPU cores, for DMC at the default size


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
    t2, c2 = time.perf_counter(), cpu_seconds()
    names = render_query_clips(env, traj, starts[0], traj, starts[1], length, out, "pair", cfg)
    t3, c3 = time.perf_counter(), cpu_seconds()
    return {"fps": 2 * length / (t1 - t0), "encode": t2 - t1, "pair": t3 - t2, "cpu": c3 - c2,
            "kb": sum((out / n).stat().st_size for n in names) / 2 / 1024}


def cpu_seconds() -> float:
    """CPU time of this process (the renderer's threads too) and of its finished children
    (ffmpeg): on a busy host, the pair's own cost, whatever its share of the cores."""
    own, children = (resource.getrusage(who) for who in
                     (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="dmc:cheetah_run",
                   help="dmc:<domain>_<task> | metaworld:<name>")
    p.add_argument("--size", default=DEFAULT_CLIP_SIZE,
                   help="clip size, WIDTHxHEIGHT (or one number for a square)")
    p.add_argument("--sizes", action="store_true",
                   help="time the default settings at every run clip size instead")
    p.add_argument("--length", type=int, default=50, help="steps per segment")
    p.add_argument("--pairs", type=int, default=5, help="timed pairs per setting (median)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    width, _, height = args.size.partition("x")
    size = {"width": int(width), "height": int(height or width)}
    if args.sizes:
        settings = {name: ClipConfig(width=w, height=h) for name, (w, h) in CLIP_SIZES.items()}
    else:
        settings = {
            "model's own quality": ClipConfig(**size, shadow_size=None, multisamples=None,
                                              slices=None, stacks=None, reflections=True),
            "shadow 512, no MSAA": ClipConfig(**size, slices=None, stacks=None,
                                              reflections=True),
            "+ 12 x 8 facets": ClipConfig(**size, reflections=True),
            "+ no reflections (default)": ClipConfig(**size),
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
    where = "each run clip size" if args.sizes else f"{size['width']}x{size['height']}"
    print(f"{args.task}: {args.pairs} pairs of 2 x {args.length} frames at {where}, "
          f"MUJOCO_GL={os.environ['MUJOCO_GL']}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.2f}, CPU time stolen by the host {steal:.0%}")
    print(f"{'settings':<27} {'render fps':>10} {'encode s/pair':>13} {'pair s':>7} "
          f"{'CPU s':>6} {'kB/clip':>7}")
    for name, m in med.items():
        print(f"{name:<27} {m['fps']:>10.1f} {m['encode']:>13.3f} {m['pair']:>7.3f} "
              f"{m['cpu']:>6.3f} {m['kb']:>7.1f}")
    if args.sizes:
        verdict = "met" if med[DEFAULT_CLIP_SIZE]["pair"] <= TARGET_S else "missed"
        print(f"target: {DEFAULT_CLIP_SIZE} pair <= {TARGET_S:.1f} s -> {verdict}")
        for env in envs.values():
            env.close()
        return
    own, fast, facets, default = med.values()
    for name, m in (("shadow 512, no MSAA", fast), ("12 x 8 facets", facets),
                    ("default", default)):
        print(f"ratio {name} / own: render fps {m['fps'] / own['fps']:.2f}x, "
              f"pair time {m['pair'] / own['pair']:.2f}x")
    verdict = "met" if default["pair"] <= TARGET_S else "missed"
    print(f"target: default pair <= {TARGET_S:.1f} s -> {verdict}")
    for env in envs.values():
        env.close()


if __name__ == "__main__":
    main()

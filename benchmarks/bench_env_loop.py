"""Environment-loop overhead: the raw simulator's step against our loop's per-step work.

Raw: dm_control's `suite.load(domain, task)` env stepped with a uniform random action (reset at
its time limit), or for Metaworld the MT1 env's own `step` (reset at its 500-step limit).
Ours: exactly what `trainer.loop.TrainingRun.train` does per step apart from SAC updates --
`agent.act` (the small preset's 256 x 2 actor, NumPy path on CPU), `env.physics_state()`,
`env.step`, `ReplayBuffer.add`, `EpisodeRecorder.record`, and at episode end `finish`, the
trajectory pool and `reset`. The ratio is ours/raw in steps per second.

    .venv/bin/python benchmarks/bench_env_loop.py                       # dmc:cheetah_run
    .venv/bin/python benchmarks/bench_env_loop.py --task dmc:quadruped_walk
    .venv/bin/python benchmarks/bench_env_loop.py --task metaworld:door-open
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # as the CLI does; before mujoco is imported

import numpy as np
import torch

from runvocab.config import build_config
from trainer.envs import _dmc_suite, _dmc_tasks, _mt1, make_env
from trainer.replay_buffer import ReplayBuffer
from trainer.sac import SAC
from trainer.trajectories import EpisodeRecorder, TrajectoryPool


def raw_dmc(name: str, seed: int):
    # trainer.envs' suite: the same dm_control, with its numpy-2 fix for quadruped's sensors.
    domain, task = _dmc_tasks()[name]
    env = _dmc_suite().load(domain, task, task_kwargs={"random": seed})
    spec = env.action_spec()
    rng = np.random.default_rng(seed)
    env.reset()

    def run(steps: int, clock=None) -> None:
        for _ in range(steps):
            if clock:
                clock("loop")
            done = env.step(rng.uniform(spec.minimum, spec.maximum)).last()
            if clock:
                clock("env.step")
            if done:
                env.reset()
                if clock:
                    clock("episode end")

    return run


def raw_metaworld(name: str, seed: int):
    env_cls, variants = _mt1(name)
    env = env_cls()
    env.seed(seed)
    env.set_task(variants[0])
    env.reset()
    low, high = env.action_space.low, env.action_space.high
    rng = np.random.default_rng(seed)

    def run(steps: int, clock=None) -> None:
        for _ in range(steps):
            if clock:
                clock("loop")
            truncated = env.step(rng.uniform(low, high))[3]
            if clock:
                clock("env.step")
            if truncated:  # at its own 500-step limit, past which it raises
                env.reset()
                if clock:
                    clock("episode end")

    return run


def ours(task: str, seed: int):
    """The per-step body of TrainingRun.train (algo sac, no updates), on our own objects."""
    cfg = build_config(task, "small", {"seed": seed})
    env = make_env(task, seed)
    device = torch.device("cpu")
    agent = SAC(env.obs_dim, env.action_dim, cfg.sac, device)
    buffer = ReplayBuffer(env.obs_dim, env.action_dim, cfg.replay_capacity, device, seed)
    pool = TrajectoryPool(cfg.feedback.pool_trajectories)
    env.reset()
    recorder = EpisodeRecorder(env.obs_dim, env.action_dim, len(env.physics_state()),
                               env.episode_length)
    rng = np.random.default_rng(seed)
    state = {"obs": env.reset(), "episode": 0}

    def run(steps: int, clock=None) -> None:
        obs, episode = state["obs"], state["episode"]
        for _ in range(steps):
            if clock:
                clock("loop")
            action = agent.act(obs, rng).astype(np.float32)
            if clock:
                clock("act")
            physics = env.physics_state()
            if clock:
                clock("physics_state")
            result = env.step(action)
            if clock:
                clock("env.step")
            buffer.add(obs, action, result.reward, result.reward, result.obs)
            recorder.record(obs, action, result.reward, physics, result.success)
            if clock:
                clock("store")
            obs = result.obs
            if result.done:
                pool.add(recorder.finish(episode, env.episode_context()))
                episode += 1
                obs = env.reset()
                if clock:
                    clock("episode end")
        state["obs"], state["episode"] = obs, episode

    return run


def breakdown(run, steps: int) -> dict[str, float]:
    """Microseconds per step spent in each piece, timed inside the loop itself (one extra
    timer call per piece; "loop" is what is left: the Python loop and the timers)."""
    totals: dict[str, float] = {}
    last = [time.perf_counter()]

    def clock(name: str) -> None:
        now = time.perf_counter()
        totals[name] = totals.get(name, 0.0) + now - last[0]
        last[0] = now

    run(steps, clock)
    return {k: v / steps * 1e6 for k, v in totals.items()}


def rate(run, steps: int) -> float:
    start = time.perf_counter()
    run(steps)
    return steps / (time.perf_counter() - start)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="dmc:cheetah_run",
                   help="dmc:<domain>_<task> | metaworld:<name>")
    p.add_argument("--steps", type=int, default=10_000, help="steps per timed repeat")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats per side (median)")
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(args.threads)

    family, name = args.task.split(":", 1)
    raw = raw_dmc(name, args.seed) if family == "dmc" else raw_metaworld(name, args.seed)
    run = ours(args.task, args.seed)
    warmup = min(1000, args.steps)
    raw(warmup)
    run(warmup)
    raw_rates, our_rates = [], []
    for r in range(args.repeats):
        # Alternate who goes first so drift (thermal, other load) hits both alike.
        for side in ((raw, raw_rates), (run, our_rates))[:: 1 if r % 2 == 0 else -1]:
            side[1].append(rate(side[0], args.steps))
    raw_rate, our_rate = statistics.median(raw_rates), statistics.median(our_rates)

    print(f"{args.task}: {args.steps} steps x {args.repeats} repeats, torch "
          f"{torch.get_num_threads()} threads, load average {os.getloadavg()[0]:.2f}")
    print(f"{'loop':<44} {'steps/s':>9} {'us/step':>8}")
    raw_name = "raw " + ("dm_control" if family == "dmc" else "metaworld") + " env.step"
    print(f"{raw_name:<44} {raw_rate:>9.0f} {1e6 / raw_rate:>8.1f}")
    print(f"{'ours: act + step + buffer.add + record':<44} {our_rate:>9.0f} "
          f"{1e6 / our_rate:>8.1f}")
    print(f"ratio ours/raw: {our_rate / raw_rate:.2f}")
    for label, fn in (("raw", raw), ("ours", run)):
        pieces = breakdown(fn, args.steps)
        print(f"{label} per step (us): " + ", ".join(f"{k} {v:.1f}" for k, v in pieces.items()))


if __name__ == "__main__":
    main()

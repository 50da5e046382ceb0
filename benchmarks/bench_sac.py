"""SAC gradient-update throughput: trainer.sac.SAC against Stable-Baselines3's SAC.

Both run in this one process on the same torch thread count, with the same network sizes, batch
size, learning rate, tau, target period, gamma, initial temperature and observation/action
dimensions (DMC cheetah: 17 and 6). Each samples its own replay buffer, pre-filled with the same
random transitions, so an "update" is sample + critic + actor + temperature (+ target every 2nd).

On a CUDA device (`--device cuda`) a third side runs our update replayed from CUDA graphs
(`sac.cuda_graph`, trainer/graphed_update.py); every timed block ends with a device sync.

    .venv/bin/python benchmarks/bench_sac.py                      # both presets
    .venv/bin/python benchmarks/bench_sac.py --hidden 256 --layers 2 --batch 256
    python3 benchmarks/bench_sac.py --device cuda                 # SB3, eager, graphed
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import torch
from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.logger import configure

from runvocab.config import SACConfig
from trainer.replay_buffer import ReplayBuffer
from trainer.sac import SAC

OBS_DIM, ACTION_DIM = 17, 6
# (hidden, layers, batch, timed updates per repeat): our small preset, then the paper's DMC sizes.
PRESETS = [(256, 2, 256, 300), (1024, 2, 1024, 20)]


class BoxEnv(gym.Env):
    """Only there to give SB3 its spaces; never stepped."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)


def random_transitions(n: int, seed: int, obs_dim: int = OBS_DIM, action_dim: int = ACTION_DIM):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    next_obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    action = rng.uniform(-1, 1, (n, action_dim)).astype(np.float32)
    reward = rng.random(n).astype(np.float32)
    return obs, action, reward, next_obs


def make_sb3(cfg: SACConfig, data, device: torch.device) -> SB3SAC:
    n = len(data[0])
    arch = [cfg.hidden_dim] * cfg.hidden_layers
    model = SB3SAC(
        "MlpPolicy", BoxEnv(), learning_rate=cfg.lr, buffer_size=n, learning_starts=0,
        batch_size=cfg.batch_size, tau=cfg.tau, gamma=cfg.gamma,
        ent_coef=f"auto_{cfg.init_temperature}", target_update_interval=cfg.target_update_every,
        policy_kwargs={"net_arch": {"pi": arch, "qf": arch}}, device=str(device), seed=0,
    )
    model.set_logger(configure(None, []))  # train() records its losses somewhere
    rb = model.replay_buffer
    obs, action, reward, next_obs = data
    rb.observations[:, 0] = obs
    rb.actions[:, 0] = action
    rb.rewards[:, 0] = reward
    rb.next_observations[:, 0] = next_obs
    rb.dones[:] = 0
    rb.full, rb.pos = True, 0
    return model


def make_ours(cfg: SACConfig, data, device: torch.device) -> tuple[SAC, ReplayBuffer]:
    """Our SAC and a replay buffer filled with `data` (its sizes are the data's)."""
    n, obs_dim, action_dim = len(data[0]), data[0].shape[1], data[1].shape[1]
    agent = SAC(obs_dim, action_dim, cfg, device)
    buffer = ReplayBuffer(obs_dim, action_dim, n, device, seed=0)
    obs, action, reward, next_obs = (torch.from_numpy(x).to(device) for x in data)
    buffer.obs[:], buffer.action[:], buffer.next_obs[:] = obs, action, next_obs
    buffer.reward[:, 0] = buffer.true_reward[:, 0] = reward
    buffer.size = n
    return agent, buffer


def timed(run: Callable[[int], None], updates: int, device: torch.device) -> float:
    """Updates per second of `run(updates)`, the device's work included."""
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    run(updates)
    if device.type == "cuda":
        torch.cuda.synchronize()
    return updates / (time.perf_counter() - start)


def sb3_side(model: SB3SAC, batch: int) -> Callable[[int], None]:
    return lambda n: model.train(gradient_steps=n, batch_size=batch)


def our_side(agent: SAC, buffer: ReplayBuffer, batch: int) -> Callable[[int], None]:
    def run(n: int) -> None:
        for _ in range(n):
            agent.update(buffer.sample(batch))
    return run


def bench(hidden: int, layers: int, batch: int, updates: int, repeats: int, warmup: int,
          buffer_size: int, device: torch.device, tf32: bool = False) -> dict[str, float]:
    """The median updates/s of each side: SB3, ours (eager) and, on CUDA, ours graphed."""
    cfg = SACConfig(hidden_dim=hidden, hidden_layers=layers, batch_size=batch, lr=5e-4,
                    tau=0.01, target_update_every=2, actor_update_every=1, gamma=0.99,
                    init_temperature=0.2, tf32=tf32)
    data = random_transitions(buffer_size, seed=0)
    torch.manual_seed(0)
    sides = {"SB3": sb3_side(make_sb3(cfg, data, device), batch),
             "ours": our_side(*make_ours(cfg, data, device), batch)}
    if device.type == "cuda":
        graphed = dataclasses.replace(cfg, cuda_graph=True)
        sides["graphed"] = our_side(*make_ours(graphed, data, device), batch)
    for run in sides.values():
        run(warmup)
    rates: dict[str, list[float]] = {name: [] for name in sides}
    for r in range(repeats):
        # Rotate who goes first so drift (thermal, other load) hits every side alike.
        names = list(sides)
        for name in names[r % len(names):] + names[: r % len(names)]:
            rates[name].append(timed(sides[name], updates, device))
    return {name: statistics.median(values) for name, values in rates.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hidden", type=int, help="hidden width (actor and critic); default: presets")
    p.add_argument("--layers", type=int, default=2, help="hidden layers (actor and critic)")
    p.add_argument("--batch", type=int, help="batch size; default: same as --hidden")
    p.add_argument("--updates", type=int, help="timed updates per repeat; default: per preset")
    p.add_argument("--repeats", type=int, default=5, help="timed repeats per side (median)")
    p.add_argument("--warmup", type=int, default=10, help="untimed updates per side first")
    p.add_argument("--buffer", type=int, default=50_000, help="pre-filled random transitions")
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="where both sides train (cuda adds the graphed side)")
    p.add_argument("--tf32", action="store_true",
                   help="on cuda, every side's float32 matrix products in TF32 (sac.tf32)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda, but torch finds no CUDA device")
    if args.tf32 and device.type != "cuda":
        raise SystemExit("error: --tf32 is for --device cuda (the CPU has no TF32)")

    if args.hidden is None:
        configs = PRESETS
    else:
        batch = args.batch or args.hidden
        default_updates = max(20, min(300, 300 * 256 * 256 // (args.hidden * batch)))
        configs = [(args.hidden, args.layers, batch, args.updates or default_updates)]

    where = (torch.cuda.get_device_name(device) if device.type == "cuda"
             else f"cpu, {torch.get_num_threads()} threads")
    where += ", TF32 matrix products" if args.tf32 else ""
    print(f"torch {torch.__version__}, {where}, load average {os.getloadavg()[0]:.2f}; "
          f"obs {OBS_DIM}, action {ACTION_DIM}, buffer {args.buffer}")
    graph_columns = (f" {'graphed upd/s':>14} {'graphed/ours':>13} {'graphed/SB3':>12}"
                     if device.type == "cuda" else "")
    print(f"{'hidden x layers':>15} {'batch':>6} {'updates':>8} {'SB3 upd/s':>10} "
          f"{'ours upd/s':>11} {'ours/SB3':>9}{graph_columns}")
    for hidden, layers, batch, updates in configs:
        # A graphed 1024-wide update takes about 1 ms on an H100: 20 of them, too short a block.
        updates = args.updates or (max(updates, 200) if device.type == "cuda" else updates)
        rate = bench(hidden, layers, batch, updates, args.repeats, args.warmup, args.buffer,
                     device, args.tf32)
        sb3, ours = rate["SB3"], rate["ours"]
        line = (f"{f'{hidden} x {layers}':>15} {batch:>6} {updates:>8} {sb3:>10.1f} "
                f"{ours:>11.1f} {ours / sb3:>8.2f}x")
        if "graphed" in rate:
            g = rate["graphed"]
            line += f" {g:>14.1f} {g / ours:>12.2f}x {g / sb3:>11.2f}x"
        print(line, flush=True)


if __name__ == "__main__":
    main()

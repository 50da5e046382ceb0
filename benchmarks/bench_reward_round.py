"""One feedback round's reward-model training, timed: how long a round takes at a given number
of labels, with and without SURF, and how close it runs to the machine's matrix-multiply rate.

    .venv/bin/python benchmarks/bench_reward_round.py                  # 900 labels, 1 thread
    .venv/bin/python benchmarks/bench_reward_round.py --labels 300 --epochs 10 --threads 2
    .venv/bin/python benchmarks/bench_reward_round.py --labels 300 --epochs 2 --bf16
    python3 benchmarks/bench_reward_round.py --device cuda --labels 1000 --epochs 5

The reward model is the run's (3 members of 3 x 256 on cheetah's 17 + 6 inputs, batch 128;
segments of 50 steps, or 60 with SURF, cropped to 45-55, as the presets set them). Labels and
SURF's unlabelled pairs are random segments with random answers, so no epoch stops early at
98 % training accuracy (in the sepoa-fair-small grid, S-EPOA's rounds and SURF's from the third
on never did). The
useful arithmetic of a round is counted in multiply-adds of the members' linear layers (forward,
and twice that backward where a gradient flows), and set against a plain matmul of the same
shapes timed on the same threads.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from runvocab.config import RewardConfig  # noqa: E402
from trainer.reward_model import LabelledPairs, RewardModel  # noqa: E402

OBS, ACT = 17, 6
SEGMENT, SURF_SEGMENT = 50, 60
"""the presets' segment lengths, without SURF and with it (cropped to 45-55)"""


def random_pairs(n: int, length: int, rng: np.random.Generator) -> LabelledPairs:
    pairs = LabelledPairs()
    for _ in range(n):
        pairs.add(*(rng.normal(size=(length, OBS + ACT)).astype(np.float32) for _ in range(2)),
                  float(rng.integers(2)))
    return pairs


def macs_per_row(cfg: RewardConfig) -> int:
    """Multiply-adds of one member on one (s, a) row."""
    d, w = OBS + ACT, cfg.hidden_dim
    return d * w + (cfg.hidden_layers - 1) * w * w + w


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_gflops(rows: int, width: int, device: torch.device, repeats: int = 20) -> float:
    a, b = torch.randn(rows, width, device=device), torch.randn(width, width, device=device)
    torch.mm(a, b)
    synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        torch.mm(a, b)
    synchronize(device)
    return 2 * rows * width * width * repeats / (time.perf_counter() - start) / 1e9


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--labels", type=int, default=900)
    p.add_argument("--epochs", type=int, default=3, help="epochs timed (a run trains up to 50)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--bf16", action="store_true",
                   help="also time each round with `reward.bf16` (bfloat16 autocast), and "
                   "print its time against float32's")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda, but torch finds no CUDA device")
    rng = np.random.default_rng(0)
    pool = rng.normal(size=(4096, SURF_SEGMENT, OBS + ACT)).astype(np.float32)

    def unlabelled(n: int) -> tuple[np.ndarray, np.ndarray]:
        i, j = rng.integers(len(pool), size=(2, n))
        return pool[i], pool[j]

    peak = matmul_gflops(128 * SEGMENT * 2, RewardConfig().hidden_dim, device)
    where = (torch.cuda.get_device_name(device) if device.type == "cuda"
             else f"{args.threads} thread(s)")
    print(f"torch {torch.__version__}, {where}; {args.labels} labels, "
          f"{args.epochs} epochs timed; plain matmul {peak:.1f} GFLOP/s")
    float32: dict[bool, float] = {}
    for surf, bf16 in [(surf, bf16) for surf in (False, True)
                       for bf16 in ((False, True) if args.bf16 else (False,))]:
        pairs = random_pairs(args.labels, SURF_SEGMENT if surf else SEGMENT, rng)
        cfg = dataclasses.replace(RewardConfig(), surf=surf, max_epochs=args.epochs,
                                  stop_accuracy=1.01, bf16=bf16)
        model = RewardModel(OBS, ACT, cfg, device, seed=0)
        synchronize(device)
        start = time.perf_counter()
        model.train_round(pairs, unlabelled if surf else None)
        synchronize(device)
        seconds = time.perf_counter() - start
        if bf16:
            print(f"{'SURF' if surf else 'plain':5s}, bf16: {seconds / args.epochs:6.2f} s per "
                  f"epoch; float32/bf16 {float32[surf] / seconds:.2f}x")
            continue
        float32[surf] = seconds
        e, per_row = cfg.ensemble_size, macs_per_row(cfg)
        crop = (cfg.surf_crop_min + cfg.surf_crop_max) / 2 if surf else SEGMENT
        labelled = args.labels * 2 * crop * e * per_row * 3  # forward and backward
        # SURF's pseudo-labels: a forward pass over the uncropped unlabelled pairs
        pseudo = (args.labels * cfg.surf_unlabelled_ratio * 2 * SURF_SEGMENT * e * per_row
                  if surf else 0)
        gflop = 2 * (labelled + pseudo) * args.epochs / 1e9
        print(f"{'SURF' if surf else 'plain':5s}: {seconds / args.epochs:6.2f} s per epoch, "
              f"{50 * seconds / args.epochs:6.0f} s per 50-epoch round; at least "
              f"{gflop / seconds:5.1f} GFLOP/s of counted arithmetic "
              f"({gflop / seconds / peak:.0%} of the matmul rate; SURF's confident pairs, "
              "forwarded again, not counted)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""APS's particle-entropy reward, three ways of computing its pairwise distances: how long each
takes and how far its reward is from the one pretraining uses now.

    .venv/bin/python benchmarks/bench_knn.py
    python3 benchmarks/bench_knn.py --device cuda      # on a GPU host (gpu_check.sh knn)

`particle_entropy` (trainer/skills/common.py) asks `torch.cdist` for its direct kernel
(`donot_use_mm_for_euclid_dist`): exact, and on an H200 40 % of paper-preset APS pretraining's
GPU time (benchmarks/README.md, profile_steps.py --pretraining). The candidates, on one batch of
features (rows x dims, as APS's successor features at the presets' batches):
- `direct`: that kernel, the reference;
- `matmul`: `cdist`'s matrix-product form (|a|^2 + |b|^2 - 2ab, inexact near zero distance);
- `broadcast`: the norm of the broadcast differences, URLB's own expression.
Printed per size: the median time of a call over `--repeats` (the device synchronised around
each), the largest difference of its distances and of its reward from the reference, and the
share of rows whose k nearest neighbours are the reference's (k = skill.knn_k, 12).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import torch  # noqa: E402

from trainer.skills.common import knn_reward  # noqa: E402

K = 12
CLIP = 1e-4
WAYS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "direct": lambda h: torch.cdist(h, h, compute_mode="donot_use_mm_for_euclid_dist"),
    "matmul": lambda h: torch.cdist(h, h, compute_mode="use_mm_for_euclid_dist"),
    "broadcast": lambda h: (h[:, None, :] - h[None, :, :]).norm(dim=-1),
}


def reward(dist: torch.Tensor) -> torch.Tensor:
    """particle_entropy's reward from the distances, with m = 1 (no running statistics)."""
    return knn_reward(dist, K, clip=CLIP)


def timed(way: Callable[[torch.Tensor], torch.Tensor], h: torch.Tensor, repeats: int) -> float:
    """Median seconds of one call of `way` and its reward."""
    times = []
    for _ in range(repeats):
        if h.is_cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        reward(way(h))
        if h.is_cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--sizes", default="256x10,1024x10,1024x64",
                   help="ROWSxDIMS,... (APS's features: 10 dims; batch 256 small, 1024 paper)")
    args = p.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda, but torch finds no CUDA device")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    name = torch.cuda.get_device_name() if args.device == "cuda" else f"{args.threads} thread(s)"
    print(f"particle-entropy distances on {args.device} ({name}), torch {torch.__version__}, "
          f"median of {args.repeats} calls, k = {K}")
    print(f"{'size':>9} {'way':>9} {'ms':>8} {'x direct':>8} {'max |d - ref|':>13} "
          f"{'max |r - ref|':>13} {'same kNN':>8}")
    generator = torch.Generator().manual_seed(0)
    for size in args.sizes.split(","):
        rows, dims = (int(n) for n in size.split("x"))
        h = (torch.randn(rows, dims, generator=generator) * 3).to(device)
        ref = WAYS["direct"](h)
        ref_reward = reward(ref)
        ref_idx = ref.topk(K, dim=1, largest=False).indices.sort(dim=1).values
        base = timed(WAYS["direct"], h, args.repeats)
        for label, way in WAYS.items():
            dist = way(h)
            idx = dist.topk(K, dim=1, largest=False).indices.sort(dim=1).values
            seconds = base if label == "direct" else timed(way, h, args.repeats)
            print(f"{size:>9} {label:>9} {seconds * 1e3:8.3f} {base / seconds:8.2f} "
                  f"{(dist - ref).abs().max().item():13.2e} "
                  f"{(reward(dist) - ref_reward).abs().max().item():13.2e} "
                  f"{(idx == ref_idx).all(dim=1).float().mean().item():8.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

#!/bin/bash
# The GPU figures of the training-speed work, in one prepared run on a GPU host (about 6
# minutes on an H100/H200): the graphed update's CUDA test, SAC updates/s (SB3, eager,
# graphed) at both sizes, whole-run steps/s eager against graphed, and EGL rendering. Every
# figure is written to $OUT as it comes, so a run stopped at its limit still leaves them.
#
# Here, once, from the project's root (wheels for the host, which has torch but no index):
#   bash ../shared/gpu/prepare.sh pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 packaging==26.4
# There, with .gpu carried along:
#   OUT=/somewhere bash benchmarks/gpu_check.sh
set -uo pipefail
: "${OUT:?set OUT to a folder for the figures}"
source .gpu/device-env.sh || exit 1
step() { echo "== $1" | tee -a "$OUT/summary.txt"; }
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$OUT/device.txt" 2>&1
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())" \
    >> "$OUT/device.txt" 2>&1
step "graphed update equals eager on CUDA"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/trainer/test_graphed_update.py \
    > "$OUT/test_graphed_update.txt" 2>&1; tail -1 "$OUT/test_graphed_update.txt" >> "$OUT/summary.txt"
step "SAC updates/s, SB3 / eager / graphed"
timeout 240 python3 benchmarks/bench_sac.py --device cuda --threads 4 \
    > "$OUT/bench_sac.txt" 2>&1; tail -3 "$OUT/bench_sac.txt" >> "$OUT/summary.txt"
step "whole run, paper preset PEBBLE, 12 000 steps, eager / graphed"
timeout 300 python3 benchmarks/bench_run.py --device cuda --preset paper --algo pebble \
    --steps 12000 --threads 4 --from-step 10000 > "$OUT/bench_run.txt" 2>&1
tail -3 "$OUT/bench_run.txt" >> "$OUT/summary.txt"
step "EGL rendering"
timeout 60 python3 -m sepoa.cli doctor --backend egl > "$OUT/doctor.txt" 2>&1
tail -2 "$OUT/doctor.txt" >> "$OUT/summary.txt"
cat "$OUT/summary.txt"

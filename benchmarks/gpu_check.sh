#!/bin/bash
# The GPU figures of the training-speed work, in prepared runs on a GPU host. Steps:
#   test    the CUDA tests: replayed graphs give the eager update's parameters; a step waits
#           for the GPU once
#   sac     SAC updates/s, SB3 / eager / graphed, at both sizes
#   run     whole-run steps/s, eager against graphed (paper preset PEBBLE)
#   doctor  EGL rendering
#   shared  N runs sharing the GPU against one alone (`experiment run --device cuda`), timed
#           over steps 11-14 k: after round 0 (at 10 k) and the evaluation at 10 k
#   tf32    `sac` and `shared` again with TF32 matrix products (`sac.tf32`)
#   mps     `shared` (graphed, TF32) with CUDA's Multi-Process Service running: N processes'
#           kernels in one GPU context instead of contexts taking turns (time-slicing)
#   sepoa   whole-run steps/s of a paper-preset S-EPOA run over steps 22-62 k, two feedback
#           rounds and four evaluations included (graphed, TF32)
#   sepoa32 the same in float32, the default
#   profile 1 000 steps of a paper-preset PEBBLE run after round 0 under torch's profiler
#           (graphed, TF32): how busy the GPU is, and the ops that hold the time
#   reward  one round's reward training on the GPU at 100 and 1 000 labels, plain and SURF
#   pretrain  APS skill pretraining steps/s at the paper's sizes, 12 000 steps (graphed, TF32)
#   tf32learn  learning with TF32: specs/paper/tf32-learning.toml (SAC oracle, float32 / TF32,
#           4 seeds each, 100 k steps), its 8 runs sharing the GPU under MPS; the runs' result
#           files come back in $OUT/tf32-learning (`sepoa report` on them here)
#   grid    the paper's DMC grid's throughput (specs/paper/dmc-grid.toml): every algorithm, N = 1,
#           4 and 8 runs sharing the GPU under MPS, timed in the learning phase, one row each
#           to $OUT/grid/throughput.csv as it comes (benchmarks/grid_throughput.py); GRID_TASKS
#           (default dmc:cheetah_run) and GRID_BUDGET (seconds, default 480) size one call,
#           and a later call with the same $OUT/grid goes on with the rows still missing
#   knn     APS's particle-entropy distances three ways (benchmarks/bench_knn.py): the direct
#           cdist kernel pretraining uses, cdist's matrix-product form, the broadcast norm
#   skillsizes  which of the two widths' differences carries skill quality (exploratory, seed
#           10, 100 k steps, two pretrainings at once): the paper preset with batch 256, and with
#           256-wide nets (batch 1 024); each snapshot's quality against the small preset's
#           (CPU) and the paper's at 100 k; what SKILLS_LIMIT seconds (default 540) reach
#           comes back in $OUT/skillsizes.tar.gz
#   skills  skill quality against APS pretraining length at the paper's width: 2 seeds at
#           once on cheetah_run, snapshots at 100 k, 200 k and 500 k on the way to 1 M, each
#           measured as 50 random skills against random actions; the quality files reached
#           within SKILLS_LIMIT seconds (default 540) come back in $OUT/skills.tar.gz
#   baseline  whole-run steps/s of paper-preset PEBBLE after round 0 (graphed, TF32), the code
#           in $BASELINE (default .baseline) against this checkout's, one after the other: what
#           a change to the step did on this GPU (now: against 3628eb1, r_hat of a new
#           transition on the host, act's soft clamp on the host, the buffer's row in one copy,
#           the update before the simulator's step; 8846c94 measured e1d84f1, one wait a step)
# The `shared`, `tf32` and `sepoa` steps also sample the GPU's utilisation twice a second
# (gpu_util_<step>.csv): whether N runs leave the GPU idle between their kernels.
# No step named: test sac run doctor. On an H100, `test sac run shared doctor` took 406 s in one
# call and `test doctor tf32` 234 s. Every figure is written to $OUT as it comes, so a run
# stopped at its limit still leaves them.
#
# Here, once, from the project's root (wheels for the host, which has torch but no index; the
# queue's packages are for `shared`, whose runs go through `sepoa experiment run`):
#   bash ../shared/gpu/prepare.sh pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 packaging==26.4 \
#       SQLAlchemy==2.0.58 greenlet==3.5.6 alembic==1.20.1 Mako==1.4.3 MarkupSafe==3.0.4
# For `baseline`, the code to compare with, here (ignored by git, carried with .gpu):
#   grep -qx /.baseline/ .git/info/exclude || echo /.baseline/ >> .git/info/exclude
#   rm -rf .baseline && mkdir .baseline && git archive 3628eb1 | tar -x -C .baseline
# There, with .gpu carried along:
#   OUT=/somewhere bash benchmarks/gpu_check.sh [STEP ...]
set -uo pipefail
: "${OUT:?set OUT to a folder for the figures}"
steps=("$@")
[ ${#steps[@]} -eq 0 ] && steps=(test sac run doctor)
for step in "${steps[@]}"; do
    case "$step" in test|sac|run|doctor|shared|tf32|mps|sepoa|sepoa32|profile|reward|pretrain|baseline|tf32learn|grid|skills|knn|skillsizes)
        ;;
    *) echo "unknown step $step; valid: test sac run doctor shared tf32 mps sepoa sepoa32" \
            "profile reward pretrain baseline tf32learn grid skills knn skillsizes" >&2
       exit 2 ;; esac
done
source .gpu/device-env.sh || exit 1
say() { echo "== $1" | tee -a "$OUT/summary.txt"; }
sampling() {  # sampling FILE COMMAND...: the command, with the GPU's utilisation sampled beside it
    local file=$1; shift
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv,noheader \
        -lms 500 > "$file" 2>&1 &
    local sampler=$!
    "$@"
    kill "$sampler" 2>/dev/null
    awk -F', ' '{gsub(/ %/, "", $2); n++; s += $2} END {if (n) printf "GPU utilisation: mean %.0f %% over %d samples\n", s / n, n}' \
        "$file" >> "$OUT/summary.txt"
}
shared_runs() {  # shared_runs TXT CSV [--set KEY=VALUE ...]: 1 and 4 paper-preset PEBBLE runs
    local txt=$1 csv=$2; shift 2
    sampling "$csv" \
        timeout 420 python3 benchmarks/bench_shared_device.py --device cuda --preset paper \
        --algo pebble --steps 14000 --from-step 11000 --workers 1,4 --threads 2 \
        --set sac.cuda_graph=true "$@" > "$txt" 2>&1
    tail -6 "$txt" >> "$OUT/summary.txt"
}
paper_pretraining() {  # paper_pretraining LOG FOLDER [SETTING ...]: a paper-preset APS
    # pretraining on cheetah_run in the background (graphed), within SKILLS_LIMIT seconds
    # (default 540), its snapshots and their skill quality in FOLDER, its output in LOG
    local log=$1 folder=$2; shift 2
    timeout "${SKILLS_LIMIT:-540}" python3 -m sepoa pretrain --task dmc:cheetah_run \
        --preset paper --device cuda --threads 4 --sac.cuda_graph true --no-progress \
        --skill.snapshot_dir "$folder" "$@" > "$log" 2>&1 &
}
pack_pretrainings() {  # pack_pretrainings WORK NAME: WORK's logs, quality files and per-episode
    # CSVs (not the snapshots) back as $OUT/NAME.tar.gz, one file: a call returns at most 8
    tar -czf "$OUT/$2.tar.gz" -C "$1" --exclude='*.pt' --exclude='*.partial' --exclude='*.lock' \
        --exclude='*.tmp' .
    grep -h "skill quality" "$1"/*.txt >> "$OUT/summary.txt"
}
# CUDA's Multi-Process Service for the runs that share the GPU: a user-space daemon with its own
# pipe and log folders; the GPU's settings (compute mode, MIG) stay as they are, and `quit`
# stops it afterwards.
mps_start() {  # mps_start NAME: 0 when the daemon started (its output in $OUT/NAME.txt)
    export CUDA_MPS_PIPE_DIRECTORY=/tmp/gpu-check-mps/pipe CUDA_MPS_LOG_DIRECTORY=/tmp/gpu-check-mps/log
    mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
    nvidia-cuda-mps-control -d > "$OUT/$1.txt" 2>&1 && return 0
    echo "MPS did not start: $(tail -1 "$OUT/$1.txt")" >> "$OUT/summary.txt"
    unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
    return 1
}
mps_clients() {  # mps_clients LOG_DIR NAME: the daemon's control log to $OUT/NAME_control.log
    # Its client lines say whether the runs' processes went through MPS.
    cp "$1/control.log" "$OUT/$2_control.log" 2>/dev/null
    echo "MPS control log: $(grep -ci "client" "$OUT/$2_control.log" 2>/dev/null) client lines" \
        >> "$OUT/summary.txt"
}
mps_stop() {  # mps_stop NAME
    echo quit | nvidia-cuda-mps-control >> "$OUT/$1.txt" 2>&1
    mps_clients "$CUDA_MPS_LOG_DIRECTORY" "$1"
    unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$OUT/device.txt" 2>&1
python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name())" \
    >> "$OUT/device.txt" 2>&1
for step in "${steps[@]}"; do
    case "$step" in
    test)
        say "graphed update equals eager on CUDA; a step waits for the GPU once"
        timeout 120 python3 -m pytest -q -p no:cacheprovider tests/trainer/test_graphed_update.py \
            tests/trainer/test_pick_device.py tests/trainer/test_host_syncs.py \
            > "$OUT/test_graphed_update.txt" 2>&1
        tail -1 "$OUT/test_graphed_update.txt" >> "$OUT/summary.txt" ;;
    sac)
        say "SAC updates/s, SB3 / eager / graphed"
        timeout 240 python3 benchmarks/bench_sac.py --device cuda --threads 4 \
            > "$OUT/bench_sac.txt" 2>&1
        tail -3 "$OUT/bench_sac.txt" >> "$OUT/summary.txt" ;;
    run)
        say "whole run, paper preset PEBBLE, 12 000 steps, eager / graphed"
        timeout 300 python3 benchmarks/bench_run.py --device cuda --preset paper --algo pebble \
            --steps 12000 --threads 4 --from-step 10000 > "$OUT/bench_run.txt" 2>&1
        tail -3 "$OUT/bench_run.txt" >> "$OUT/summary.txt" ;;
    baseline)
        baseline=${BASELINE:-.baseline}
        [ -f "$baseline/benchmarks/bench_run.py" ] || {
            say "no baseline code in $baseline: skipped"; continue; }
        say "whole run, paper preset PEBBLE, steps 11-13 k, graphed, TF32: $baseline / this"
        for side in "$baseline" .; do
            txt="$OUT/bench_run_$( [ "$side" = . ] && echo current || echo baseline ).txt"
            # Each tree's bench_run.py puts its own root first on the import path.
            (cd "$side" && timeout 240 python3 benchmarks/bench_run.py --device cuda \
                --preset paper --algo pebble --steps 13000 --from-step 11000 --threads 4 \
                --sides graphed --set sac.tf32=true) > "$txt" 2>&1
            tail -2 "$txt" >> "$OUT/summary.txt"
        done ;;
    doctor)
        say "EGL rendering"
        timeout 60 python3 -m sepoa doctor --backend egl > "$OUT/doctor.txt" 2>&1
        tail -2 "$OUT/doctor.txt" >> "$OUT/summary.txt" ;;
    shared)
        say "1 and 4 paper-preset PEBBLE runs sharing the GPU, steps 11-14 k (graphed updates)"
        shared_runs "$OUT/bench_shared_device.txt" "$OUT/gpu_util_shared.csv" ;;
    tf32)
        say "SAC updates/s with TF32 matrix products, SB3 / eager / graphed"
        timeout 120 python3 benchmarks/bench_sac.py --device cuda --threads 4 --tf32 \
            > "$OUT/bench_sac_tf32.txt" 2>&1
        tail -3 "$OUT/bench_sac_tf32.txt" >> "$OUT/summary.txt"
        say "1 and 4 paper-preset PEBBLE runs sharing the GPU, steps 11-14 k (graphed, TF32)"
        shared_runs "$OUT/bench_shared_tf32.txt" "$OUT/gpu_util_tf32.csv" --set sac.tf32=true ;;
    mps)
        say "1 and 4 paper-preset PEBBLE runs sharing the GPU under MPS, steps 11-14 k (graphed, TF32)"
        if mps_start mps; then
            shared_runs "$OUT/bench_shared_mps.txt" "$OUT/gpu_util_mps.csv" --set sac.tf32=true
            mps_stop mps
        fi ;;
    tf32learn)
        say "learning with TF32: SAC oracle, paper preset, float32 / TF32, 4 seeds each, 100 k steps"
        # The launcher's own MPS daemon (`--mps`), its control log in $results/mps.
        results=/tmp/gpu-check-tf32learn
        sampling "$OUT/gpu_util_tf32learn.csv" \
            timeout "${TF32LEARN_LIMIT:-500}" python3 -m sepoa experiment run \
            specs/paper/tf32-learning.toml --results "$results" --workers 8 --threads 2 \
            --device cuda --mps > "$OUT/tf32learn.txt" 2>&1
        tail -3 "$OUT/tf32learn.txt" >> "$OUT/summary.txt"
        mps_clients "$results/mps" mps_tf32learn
        # Each run's result files (not its checkpoint or TensorBoard files), finished or not.
        (cd "$results" && tar -czf "$OUT/tf32-learning.tar.gz" --exclude=checkpoint.pt \
            --exclude=tb --exclude='*.lock' tf32-learning) 2>> "$OUT/summary.txt" ;;
    sepoa|sepoa32)
        # Round 0 comes at 20 k, after the random steps and 20 rollouts; steps 22-62 k hold two
        # more rounds (40 k, 60 k) and four evaluations of 10 episodes: the rate a 1 M-step run
        # sees while its budget lasts. A 5 000-step snapshot: pretraining is not timed.
        # `sepoa32` is the same run in float32, the default (`sac.tf32` off).
        tf32=$( [ "$step" = sepoa ] && echo true || echo false )
        say "whole run, paper preset S-EPOA, steps 22-62 k (rounds and evaluations), graphed, TF32 $tf32"
        sampling "$OUT/gpu_util_$step.csv" \
            timeout 360 python3 benchmarks/bench_run.py --device cuda --preset paper \
            --algo sepoa --steps 62000 --from-step 22000 --threads 4 --sides graphed \
            --set skill.pretrain_steps=5000 --set sac.tf32=$tf32 > "$OUT/bench_run_$step.txt" 2>&1
        tail -2 "$OUT/bench_run_$step.txt" >> "$OUT/summary.txt" ;;
    profile)
        say "1 000 steps of paper-preset PEBBLE under the profiler, graphed, TF32"
        timeout 300 python3 benchmarks/profile_steps.py --device cuda --preset paper \
            --algo pebble --from-step 10500 --steps 1000 --threads 4 \
            --set sac.cuda_graph=true --set sac.tf32=true > "$OUT/profile_steps.txt" 2>&1
        grep -E "ms a step|GPU busy|torch ops on the host|host waits for" "$OUT/profile_steps.txt" \
            >> "$OUT/summary.txt" ;;
    reward)
        say "one round's reward training on the GPU, 100 and 1 000 labels"
        for labels in 100 1000; do
            timeout 120 python3 benchmarks/bench_reward_round.py --device cuda --labels $labels \
                --epochs 5 > "$OUT/bench_reward_round_$labels.txt" 2>&1
            tail -3 "$OUT/bench_reward_round_$labels.txt" >> "$OUT/summary.txt"
        done ;;
    pretrain)
        say "APS pretraining at the paper's sizes, 12 000 steps (4 000 random), graphed, TF32"
        timeout 240 python3 -m sepoa pretrain --task dmc:cheetah_run --preset paper \
            --steps 12000 --device cuda --threads 4 --sac.cuda_graph true --sac.tf32 true \
            --out /tmp/gpu-check-pretrain/aps.pt --no-progress > "$OUT/pretrain.txt" 2>&1
        cp /tmp/gpu-check-pretrain/aps.csv "$OUT/pretrain.csv" 2>/dev/null
        tail -1 "$OUT/pretrain.txt" >> "$OUT/summary.txt" ;;
    grid)
        say "DMC grid throughput: N = 1, 4, 8 runs under MPS per algorithm, learning phase"
        mkdir -p "$OUT/grid"
        if mps_start mps_grid; then
            # shellcheck disable=SC2086
            timeout $(( ${GRID_BUDGET:-480} + 120 )) python3 benchmarks/grid_throughput.py \
                measure specs/paper/dmc-grid.toml --device cuda --workers 1,4,8 \
                --tasks ${GRID_TASKS:-dmc:cheetah_run} --budget-seconds "${GRID_BUDGET:-480}" \
                --out "$OUT/grid" > "$OUT/grid/measure.txt" 2>&1
            mps_stop mps_grid
        fi
        tail -20 "$OUT/grid/measure.txt" >> "$OUT/summary.txt"
        python3 benchmarks/grid_throughput.py project specs/paper/dmc-grid.toml \
            "$OUT/grid/throughput.csv" --workers 8 >> "$OUT/summary.txt" 2>&1 ;;
    knn)
        say "particle-entropy distances: direct cdist, matrix products, broadcast norm"
        timeout 120 python3 benchmarks/bench_knn.py --device cuda > "$OUT/bench_knn.txt" 2>&1
        cat "$OUT/bench_knn.txt" >> "$OUT/summary.txt" ;;
    skillsizes)
        say "APS skill quality at 100 k, seed 10: paper width with batch 256; 256 wide, batch 1024"
        work=/tmp/gpu-check-skillsizes && mkdir -p "$work"
        paper_pretraining "$work/wide-batch256.txt" "$work/wide-batch256" --steps 100000 \
            --seed 10 --sac.batch_size 256
        paper_pretraining "$work/narrow-batch1024.txt" "$work/narrow-batch1024" --steps 100000 \
            --seed 10 --sac.hidden_dim 256 --skill.hidden_dim 256
        wait
        pack_pretrainings "$work" skillsizes ;;
    skills)
        say "APS skill quality at the paper's width, 2 seeds, snapshots at 100/200/500 k (graphed)"
        work=/tmp/gpu-check-skills && mkdir -p "$work"
        for seed in 10 11; do
            paper_pretraining "$work/seed-$seed.txt" "$work" --steps 1000000 --seed $seed \
                --snapshots-at 100000,200000,500000
        done
        wait
        pack_pretrainings "$work" skills ;;
    esac
done
cat "$OUT/summary.txt"

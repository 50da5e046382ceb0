#!/bin/bash
# Part of an experiment grid, trained on a lent GPU host in one command of a few minutes.
# Runs that finish come back in $OUT/runs.tar.gz as folders of a results folder; untarred into
# the grid's own results folder, `sepoa experiment run SPEC --results <results>` counts them as
# finished ("finished before"). A run that does not finish in time is lost there (nothing is
# resumed across devices); its episodes.csv comes back in $OUT/unfinished.tar.gz, for its rate.
#
# Here, once, from the project's root (wheels for the host; the queue's packages are needed):
#   bash ../shared/gpu/prepare.sh pytest==9.2.0 pluggy==1.7.0 iniconfig==2.3.1 packaging==26.4 \
#       SQLAlchemy==2.0.58 greenlet==3.5.6 alembic==1.20.1 Mako==1.4.3 MarkupSafe==3.0.4
# and, when the grid trains on a commit of its own (as every run of a grid must), its code:
#   echo /.grid-code/ >> .git/info/exclude
#   rm -rf .grid-code && mkdir .grid-code && git archive GRID_COMMIT | tar -x -C .grid-code
# There, carrying .gpu (and .grid-code):
#   OUT=/somewhere CODE=.grid-code LIMIT=540 WORKERS=1 bash scripts/grid_part_on_gpu.sh \
#       specs/small/sepoa-fair.toml --variant PEBBLE --seed 17
# Back here:
#   tar -xzf <files>/runs.tar.gz -C <results>
# LIMIT (seconds) bounds the training, so that packing the results fits the command's limit.
# WORKERS (default 1): runs trained at once. On an H100, 4 runs sharing the GPU made no more
# steps/s together than one alone (benchmarks/README.md), so more workers share one run's rate
# and may finish none in the time.
# MPS=1: the workers' processes share one GPU context through CUDA's Multi-Process Service, a
# daemon of this command's own (its pipe and log folders private, the GPU's settings untouched),
# told to quit at the end. 4 paper-preset runs made 2.87x one run's steps/s together under MPS
# and 1.33x without (H200, graphed, benchmarks/README.md); small-preset eager runs under MPS
# are not measured, so give the first such call a few runs and read their rates in
# unfinished.tar.gz.
# The workers train on each run's own device (`auto`: the GPU); DEVICE=D passes `--device D`,
# for code whose `experiment run` has that option.
set -uo pipefail
: "${OUT:?set OUT to a folder for what comes back}"
[ $# -ge 1 ] || { echo "usage: OUT=... bash $0 SPEC [--variant LABEL ...] [--seed N ...]" >&2; exit 2; }
spec=$1; shift
code=$(cd "${CODE:-.}" && pwd) || exit 2
[ -f "$code/$spec" ] || { echo "no spec $spec under $code" >&2; exit 2; }
limit=${LIMIT:-540}
workers=${WORKERS:-1}
device=(); [ -n "${DEVICE:-}" ] && device=(--device "$DEVICE")
source .gpu/device-env.sh || exit 1
export PYTHONPATH=$code:$PYTHONPATH  # the grid's code first
results=$(mktemp -d)
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$OUT/device.txt" 2>&1
echo "code: $code; spec $spec $*; $workers workers ${device[*]}; limit ${limit}s" >> "$OUT/device.txt"
if [ "${MPS:-0}" = 1 ]; then
    export CUDA_MPS_PIPE_DIRECTORY=$results/mps/pipe CUDA_MPS_LOG_DIRECTORY=$results/mps/log
    mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
    nvidia-cuda-mps-control -d > "$OUT/mps.txt" 2>&1 \
        || { echo "MPS did not start: $(tail -1 "$OUT/mps.txt")" | tee -a "$OUT/device.txt"; exit 1; }
    echo "MPS daemon started" >> "$OUT/device.txt"
fi
start=$(date +%s)
(cd "$code" && timeout --signal=TERM --kill-after=20 "$limit" python3 -m sepoa experiment run \
    "$spec" --results "$results" --workers "$workers" --threads 1 "${device[@]}" "$@") \
    > "$OUT/launch.txt" 2>&1
echo "launch exited $? after $(( $(date +%s) - start )) s" >> "$OUT/launch.txt"
if [ "${MPS:-0}" = 1 ]; then
    echo quit | nvidia-cuda-mps-control >> "$OUT/mps.txt" 2>&1
    # Its client lines say whether the workers went through the daemon.
    cp "$CUDA_MPS_LOG_DIRECTORY/control.log" "$OUT/mps_control.log" 2>/dev/null
    echo "MPS control log: $(grep -ci client "$OUT/mps_control.log" 2>/dev/null) client lines" \
        >> "$OUT/device.txt"
fi
cp "$results/workers.log" "$OUT/workers.log" 2>/dev/null
cd "$results" || exit 1
# Finished runs: what the grid's report reads (no checkpoint, no TensorBoard files).
find . -name done.json -printf '%h\n' | sort > finished.txt
gpu=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)
while read -r run; do
    # config.json says `auto`: where the run actually trained is kept beside it.
    echo "${gpu:-no GPU}, $(date -u +%F) (scripts/grid_part_on_gpu.sh)" > "$run/trained_on.txt"
    for f in config.json done.json episodes.csv eval.csv rounds.csv labels.jsonl trained_on.txt; do
        [ -f "$run/$f" ] && echo "$run/$f"
    done
done < finished.txt > keep.txt
tar -czf "$OUT/runs.tar.gz" -T keep.txt
find . -name episodes.csv -printf '%h\n' | sort | comm -23 - finished.txt \
    | sed 's|$|/episodes.csv|' > unfinished.txt
tar -czf "$OUT/unfinished.tar.gz" -T unfinished.txt
echo "finished: $(wc -l < finished.txt) runs; unfinished: $(wc -l < unfinished.txt)" \
    | tee -a "$OUT/launch.txt"
cat finished.txt

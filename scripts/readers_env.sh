#!/usr/bin/env bash
# Makes .venv-readers, an environment of its own for the libraries that read a dataset export
# (d3rlpy, TorchRL; scripts/readers-requirements.txt says why they cannot share .venv), and
# keeps it while the requirements stay the same. tests/test_dataset_readers.py runs them there
# when SEPOA_READERS_PYTHON names its python (scripts/test.sh sets it).
set -euo pipefail
cd "$(dirname "$0")/.."
requirements=scripts/readers-requirements.txt
venv=.venv-readers
if [ -x "$venv/bin/python" ] && cmp -s "$requirements" "$venv/requirements.txt"; then
    exit 0
fi
rm -rf "$venv"
"${PYTHON:-python3}" -m venv "$venv"
log=$(mktemp)
# The CPU build of torch first, as scripts/setup.sh installs it (a plain requirement would pull
# several GB of CUDA packages).
if ! { "$venv/bin/python" -m pip install -q "$(grep '^torch==' "$requirements")" &&
       "$venv/bin/python" -m pip install -q -r "$requirements"; } >"$log" 2>&1; then
    cat "$log" >&2
    exit 1
fi
rm -f "$log"
cp "$requirements" "$venv/requirements.txt"
echo "readers' environment: $("$venv/bin/python" -c 'from importlib.metadata import version as v; print("d3rlpy", v("d3rlpy"), "torchrl", v("torchrl"), "gymnasium", v("gymnasium"))')"

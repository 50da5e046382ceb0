#!/usr/bin/env bash
# Sets the project and the tests' tools up from nothing (scripts/setup.sh --for-tests) and runs
# the whole test suite, the queue tests on a throwaway PostgreSQL cluster too
# (scripts/with_postgres.sh; CI must exercise it, so a cluster that cannot start fails the run).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh --for-tests
# d3rlpy and TorchRL, which tests/test_dataset_readers.py reads a dataset export with, in an
# environment of their own (their pins clash with the project's; about two minutes when new).
bash scripts/readers_env.sh
export SEPOA_READERS_PYTHON="$PWD/.venv-readers/bin/python"
export MUJOCO_GL=${MUJOCO_GL:-egl}
.venv/bin/python -m ruff check sepoa server trainer labelqueue rundata crowdstudy externalruns runviews labelstats runvocab experiments figures migrations tests benchmarks examples
.venv/bin/python -m mypy
set +e
# One pytest process per core (pytest-xdist): every test keeps its own files, ports, schema
# and queue, so they run side by side.
bash scripts/with_postgres.sh .venv/bin/python -m pytest -n auto "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
    echo "pytest collected no tests: failing on purpose" >&2
    exit 1
fi
exit "$rc"

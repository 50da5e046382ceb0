#!/usr/bin/env bash
# Installs what the app needs on a fresh Debian machine: the system libraries for off-screen
# MuJoCo rendering, a virtual environment in .venv, torch (its CPU build where no GPU is
# present), and the project with every command (`sepoa up` and the rest) and its postgres extra
# (psycopg, for a queue on a PostgreSQL server).
#
# With --for-tests (scripts/test.sh), also what the tests use: headless Chromium for the browser
# tests, PostgreSQL's server for the queue's PostgreSQL variants, docker-compose v1 to validate
# the compose file, Slurm and MUNGE for the Slurm test (which configures and starts its own
# daemons), and the project's dev extra (pytest, ruff, mypy, Stable-Baselines3, playwright).
#
# Run again, it installs only what is missing: a set-up machine takes a few seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

for_tests=false
case "${1-}" in
    --for-tests) for_tests=true ;;
    "") ;;
    *) echo "usage: bash scripts/setup.sh [--for-tests]" >&2; exit 2 ;;
esac

apt_packages=(
    libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libglfw3  # off-screen MuJoCo: EGL, OSMesa
)
extras=(postgres)
if $for_tests; then
    apt_packages+=(
        chromium        # headless browser tests (Python playwright, executable_path=/usr/bin/chromium)
        postgresql      # scripts/test.sh starts a throwaway cluster for the PostgreSQL test variants
        docker-compose  # v1: `docker-compose config` validates docker-compose.yml without an engine
        slurm-wlm munge # tests/experiments/test_slurm_cluster.py starts a throwaway one-node cluster
    )
    extras=(dev postgres)
fi
missing=()
for pkg in "${apt_packages[@]}"; do
    # "install ok installed", not just known to dpkg (a removed package keeps its config files).
    status=$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null || true)
    [[ "$status" == *" ok installed" ]] || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "installing system packages: ${missing[*]}"
    # Waits for another apt/dpkg (unattended upgrades, a parallel set-up) instead of failing.
    apt_get=(env DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600)
    [ "$(id -u)" -eq 0 ] || apt_get=(sudo "${apt_get[@]}")
    apt_log=$(mktemp)
    # Quiet unless it fails (dpkg prints several lines per package whatever -qq says).
    if ! { "${apt_get[@]}" update -qq && "${apt_get[@]}" install -y -qq --no-install-recommends \
            "${missing[@]}"; } >"$apt_log" 2>&1; then
        cat "$apt_log" >&2
        exit 1
    fi
    rm -f "$apt_log"
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
pip_install() {
    # Quiet unless it fails; drops pip's notes about configured local mirrors that are absent.
    local log
    log=$(mktemp)
    if ! .venv/bin/python -m pip install -q "$@" >"$log" 2>&1; then
        cat "$log" >&2
        return 1
    fi
    grep -v "^WARNING: Location 'file:" "$log" || true
    rm -f "$log"
}
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi >/dev/null 2>&1; then
        pip_install "torch>=2.4,<2.14"
    else
        # The CPU build: a plain requirement would pull several GB of CUDA packages.
        pip_install "torch==2.13.0" || pip_install "torch>=2.4,<2.14"
    fi
fi
# Whether the project and pyproject.toml's requirements (the given extras' too) are installed
# in versions they accept; anything missing, stale or unreadable means no, and pip installs.
installed() {
    .venv/bin/python - "$@" <<'EOF' >/dev/null 2>&1
import sys
import tomllib
from importlib.metadata import requires, version

try:
    from packaging.requirements import Requirement
except ImportError:
    from pip._vendor.packaging.requirements import Requirement


def satisfied(req: Requirement) -> bool:
    if not req.specifier.contains(version(req.name), prereleases=True):
        return False
    for extra in req.extras:  # uvicorn[standard], minari[hdf5], psycopg[binary]
        for text in requires(req.name) or []:
            sub = Requirement(text)
            if sub.marker is not None and sub.marker.evaluate({"extra": extra}) and \
                    not sub.marker.evaluate({"extra": ""}) and not satisfied(sub):
                return False
    return True


with open("pyproject.toml", "rb") as f:
    project = tomllib.load(f)["project"]
version(project["name"])
wanted = [*project["dependencies"],
          *(text for extra in sys.argv[1:] for text in project["optional-dependencies"][extra])]
reqs = [Requirement(text) for text in wanted]
sys.exit(0 if all(satisfied(r) for r in reqs if r.marker is None or r.marker.evaluate()) else 1)
EOF
}
if ! [ -x .venv/bin/sepoa ] || ! installed "${extras[@]}"; then
    pip_install -e ".[$(IFS=,; echo "${extras[*]}")]"
fi
echo "set-up done: $(.venv/bin/python -c 'import torch, mujoco, dm_control; print("torch", torch.__version__, "mujoco", mujoco.__version__)')"

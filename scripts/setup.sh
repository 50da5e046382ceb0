#!/usr/bin/env bash
# Installs everything the project needs on a fresh Debian machine: the system libraries for
# off-screen MuJoCo rendering, a virtual environment in .venv, torch, and the project itself.
set -euo pipefail
cd "$(dirname "$0")/.."

apt_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6 libglfw3)
missing=()
for pkg in "${apt_packages[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "installing system packages: ${missing[*]}"
    sudo_cmd=""
    [ "$(id -u)" -eq 0 ] || sudo_cmd="sudo"
    $sudo_cmd apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq --no-install-recommends "${missing[@]}"
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
pip_install -e ".[dev]"
echo "set-up done: $(.venv/bin/python -c 'import torch, mujoco, dm_control; print("torch", torch.__version__, "mujoco", mujoco.__version__)')"

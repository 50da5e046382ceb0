"""benchmarks/skill_quality.py run, told to go: it passes the signal on to its pretrainings,
which save their progress at the end of their episode and exit (that the same command goes on
from there, tests/trainer/test_pretrain.py checks)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SPEC = """
name = "quality"
task = "dmc:cheetah_run"
preset = "tiny"
backend = "aps"
steps = 100000
snapshots_at = [50000]
seeds = [0]
quality_skills = 0
"""


def test_a_stopped_run_leaves_each_pretraining_resumable(tmp_path: Path) -> None:
    spec = tmp_path / "quality.toml"
    spec.write_text(SPEC)
    results = tmp_path / "results"
    command = [sys.executable, str(ROOT / "benchmarks" / "skill_quality.py"), "run", str(spec),
               "--results", str(results), "--workers", "1"]
    env = os.environ | {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    run = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    snapshots = results / "quality" / "snapshots"
    deadline = time.monotonic() + 120
    while not any(len(p.read_text().splitlines()) > 1 for p in snapshots.glob("*.csv")):
        assert run.poll() is None and time.monotonic() < deadline  # an episode has ended
        time.sleep(0.1)
    run.send_signal(signal.SIGTERM)
    out, _ = run.communicate(timeout=120)
    assert "seed 0 ended with exit code 143" in out and run.returncode == 1, out
    log = (results / "quality" / "seed-0.log").read_text()
    assert "pretraining left at step" in log and "the same command goes on from there" in log
    assert list(snapshots.glob("*.pt.partial"))

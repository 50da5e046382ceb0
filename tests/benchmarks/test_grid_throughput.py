"""The grid's projected wall time from measured throughput: every run of the spec counted once,
a pair not measured borrowing its variant's rate on a measured task, the snapshots' steps
added."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

import grid_throughput  # noqa: E402


def test_the_dmc_grid_projects_from_the_rates_measured_at_n(tmp_path, capsys):
    measured = tmp_path / "throughput.csv"
    rows = [",".join(grid_throughput.COLUMNS)]
    for variant, algo in (("SAC", "sac"), ("PEBBLE", "pebble"), ("SURF", "surf"),
                          ("RUNE", "rune"), ("RIME", "rime"), ("S-EPOA", "sepoa")):
        rows.append(f"dmc:cheetah_run,{variant},{algo},8,1000.0,2.50x,80,60")
        rows.append(f"dmc:cheetah_run,{variant},{algo},1,400.0,1.00x,40,60")
    rows.append("dmc:quadruped_run,SAC,sac,8,500.0,2.00x,90,60")
    measured.write_text("\n".join(rows) + "\n")
    spec = str(ROOT / "specs" / "paper" / "dmc-grid.toml")
    assert grid_throughput.main(["project", spec, str(measured), "--workers", "8",
                                 "--pretrain-steps-per-s", "1000"]) == 0
    out = capsys.readouterr().out
    # 15 runs (3 eps x 5 seeds) of 1 M steps per task and variant: 15e6 / 1000 s = 4.17 h at
    # the borrowed cheetah rate; SAC on quadruped_run at its own 500 steps/s, 8.33 h.
    assert "dmc:walker_run         PEBBLE    15 runs    1000.0 steps/s     4.2 h (rate of " \
           "dmc:cheetah_run)" in out
    assert "dmc:quadruped_run      SAC       15 runs     500.0 steps/s     8.3 h\n" in out
    # APS: 5 seeds x (500 k cheetah + 500 k walker + 1 M + 1 M quadruped) = 15 M steps.
    assert "APS snapshots: 15,000,000 steps at 1000 steps/s: 4.2 h" in out
    total = 23 * 15e6 / 1000 / 3600 + 15e6 / 500 / 3600 + 15e6 / 1000 / 3600
    assert f"projected: {total:.1f} h (goal 48 h)" in out

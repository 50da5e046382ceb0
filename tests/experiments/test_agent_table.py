"""The report's "How the agents trained" table, on hand-written episodes.csv files: updates
by each point, the window's means of the training return, α, Q and critic loss, the seeds that
reached each point."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from experiments.agent_table import agent_markdown, agent_table
from experiments.results import load_results
from sepoa.cli import main

SPEC = """
name = "agents"
title = "Agents"
preset = "tiny"
steps = 8000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]

[variants.SAC]
algo = "sac"

[variants.S]
algo = "sepoa"
"""
HEADER = "step,episode,return,updates,alpha,q,critic_loss"


def episode_rows(first_update: int, last_step: int, scale: float) -> list[str]:
    """An episode per 1 000 steps; updates from `first_update` on, one per step; α, Q and
    critic loss empty before the first update."""
    rows = []
    for episode, step in enumerate(range(1000, last_step + 1, 1000)):
        updates = max(0, step - first_update)
        learnt = f"{0.1 / (episode + 1):.6f},{scale * step / 1000:g},{step / 8000:g}" \
            if updates else ",,"
        rows.append(f"{step},{episode},{scale * episode:g},{updates},{learnt}")
    return rows


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    folder = tmp_path / "agents"
    folder.mkdir()
    (folder / "spec.toml").write_text(SPEC)
    runs = {("SAC", 0): (1000, 8000, 1.0), ("SAC", 1): (1000, 8000, 3.0),
            ("S", 0): (5000, 8000, 2.0), ("S", 1): (5000, 5000, 2.0)}  # S s1 stopped at 5 k
    for (variant, seed), (first, last, scale) in runs.items():
        run = folder / "dmc-cheetah_run" / variant / "eps0.3" / f"s{seed}"
        run.mkdir(parents=True)
        (run / "episodes.csv").write_text("\n".join([HEADER, *episode_rows(first, last, scale)])
                                          + "\n")
        if last == 8000:
            (run / "done.json").write_text(json.dumps({"step": last}))
    return folder


def test_each_point_averages_the_window_and_counts_the_seeds_that_reached_it(
        folder: Path) -> None:
    table = agent_table(load_results(folder)).set_index(["variant", "point"])
    assert list(table.index) == [("SAC", 2000), ("SAC", 4000), ("SAC", 6000), ("SAC", 8000),
                                 ("S", 2000), ("S", 4000), ("S", 6000), ("S", 8000)]
    sac = table.loc[("SAC", 4000)]
    # Updates by step 4 000: 3 000 on both seeds.
    assert (sac["updates_mean"], sac["n"]) == (3000, 2)
    # The window (steps -1 000 to 4 000) holds episodes 0-3: returns scale x (0+1+2+3)/4, so
    # 1.5 and 4.5 on the two seeds.
    assert sac["return_mean"] == pytest.approx(3.0)
    assert sac["return_std"] == pytest.approx(math.sqrt(4.5))
    # α and Q have no value before the first update (step 1 000 has 0 updates): the window's
    # rows after it, steps 2 000-4 000.
    assert sac["alpha_mean"] == pytest.approx((0.1 / 2 + 0.1 / 3 + 0.1 / 4) / 3, rel=1e-4)
    # Q is scale x step / 1 000: 3 scale over those rows, and the scales 1 and 3 average 2.
    assert sac["q_mean"] == pytest.approx(2 * 3)
    # S before its first update at 5 000: no α, Q or loss at 2 000 or 4 000.
    assert math.isnan(table.loc[("S", 4000)]["alpha_mean"])
    # The stopped seed reached 5 000 only: the later points have the finished seed alone.
    assert table.loc[("S", 4000)]["n"] == 2 and table.loc[("S", 6000)]["n"] == 1
    assert table.loc[("S", 8000)]["updates_mean"] == 3000


def test_the_report_has_the_section_and_older_episodes_files_leave_cells_empty(
        folder: Path) -> None:
    older = folder / "dmc-cheetah_run" / "SAC" / "eps0.3" / "s1" / "episodes.csv"
    older.write_text("step,episode,return\n" + "".join(
        f"{step},{step // 1000 - 1},1.0\n" for step in range(1000, 8001, 1000)))
    assert main(["report", str(folder)]) == 0
    report = (folder / "report" / "report.md").read_text()
    assert "## How the agents trained" in report
    markdown = (folder / "report" / "agent.md").read_text()
    # Seed 1 of SAC has no updates column: the cell counts seed 0 alone.
    assert "| dmc:cheetah_run | 0.3 | 30 | SAC | 4,000 | 3000 (n=1) |" in markdown
    assert agent_markdown(agent_table(load_results(folder)).iloc[0:0], {}) \
        == "No run has logged an episode yet."

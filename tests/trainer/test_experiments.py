"""Experiment specs and the runner: expansion into run folders, clear errors for bad specs,
and real tiny runs through the runner: finished runs are skipped, a killed run resumes, a
failing run is reported while the others finish, a skill snapshot is pretrained once."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from trainer.experiments.runner import Outcome, run_spec, status_table
from trainer.experiments.spec import Spec, SpecError, load_spec

ROOT = Path(__file__).resolve().parents[2]

GRID = """
name = "grid"
preset = "tiny"
steps = 600
tasks = ["dmc:cheetah_run", "dmc:walker_run"]
eps = [0.1, 0.3]
seeds = [0, 1, 2]
budgets = [20, 30]

[overrides]
"feedback.per_round" = 10
eval_every = 200

[variants.PEBBLE]
algo = "pebble"

[variants."S-EPOA w/o pretraining"]
algo = "sepoa"
"feedback.per_round" = 5
skill.pretrain_steps = 0
"""


def write(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_grid_expands_into_one_folder_per_run(tmp_path: Path) -> None:
    spec = load_spec(write(tmp_path, GRID), check=False)
    runs = spec.runs()
    assert len(runs) == 2 * 2 * 2 * 2 * 3
    assert len({r.dir for r in runs}) == len(runs)
    run = next(r for r in runs if r.variant == "S-EPOA w/o pretraining" and r.seed == 2
               and r.eps == 0.1 and r.budget == 30 and r.task == "dmc:walker_run")
    assert run.dir == Path("dmc-walker_run/S-EPOA_w-o_pretraining/eps0.1/budget30/s2")
    # Shared overrides reach every run; the variant's win; the budget axis sets the budget.
    assert run.overrides == {"feedback.per_round": 5, "eval_every": 200,
                             "skill.pretrain_steps": 0, "feedback.budget": 30}
    cfg = run.config()
    assert (cfg.algo, cfg.seed, cfg.teacher.eps, cfg.feedback.budget) == ("sepoa", 2, 0.1, 30)
    assert cfg.feedback.per_round == 5 and cfg.skill.pretrain_steps == 0
    pebble = next(r for r in runs if r.variant == "PEBBLE")
    assert pebble.config().feedback.per_round == 10


BAD_SPECS = [
    ('[variants.PEBBLE]\nalgo = "pebble"', '[variants.X]\nalgo = "nope"',
     "[variants.\"X\"]: unknown algo 'nope'"),
    ('eval_every = 200', 'sac.width = 3', "[overrides]: unknown config field 'sac.width'"),
    ("seeds = [0, 1, 2]", "seeds = []", "'seeds' is empty"),
    ('tasks = ["dmc:cheetah_run", "dmc:walker_run"]\n', "", "missing required key 'tasks'"),
    ("eval_every = 200", "eval_every = 0.5", "'eval_every' takes int"),
    ("eval_every = 200", '"teacher.eps" = 0.1', "'teacher.eps' is set by the spec's eps"),
    ("seeds = [0, 1, 2]", "seeds = [0, 1, 1]", "'seeds' lists 1 twice"),
    ('tasks = ["dmc:cheetah_run", "dmc:walker_run"]', 'tasks = ["dmc:cheetah_rum"]',
     "unknown task 'dmc:cheetah_rum'"),
    ('[variants.PEBBLE]\nalgo = "pebble"', '[variants.PEBBLE]\nsteps = 3',
     '[variants."PEBBLE"]: missing required key \'algo\''),
]


@pytest.mark.parametrize(("old", "new", "message"), BAD_SPECS)
def test_a_bad_spec_is_refused_with_a_message_naming_the_problem(
        tmp_path: Path, old: str, new: str, message: str) -> None:
    assert old in GRID
    path = write(tmp_path, GRID.replace(old, new, 1), "bad.toml")
    with pytest.raises(SpecError) as err:
        load_spec(path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)


def test_a_bad_run_config_is_refused_before_anything_runs(tmp_path: Path) -> None:
    path = write(tmp_path, GRID.replace("eval_every = 200", '"feedback.selection" = "best"'))
    with pytest.raises(SpecError, match="unknown feedback.selection 'best'"):
        load_spec(path)


# ---------------------------------------------------------------------------------------------
# Real runs (tiny preset, real subprocesses).

TINY = """
name = "tiny"
preset = "tiny"
steps = {steps}
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = {seeds}

[overrides]
eval_every = 200
"skill.pretrain_steps" = 200
"""


def _lines() -> tuple[list[str], Callable[[str], None]]:
    lines: list[str] = []
    return lines, lines.append


@pytest.fixture(scope="module")
def finished(tmp_path_factory: pytest.TempPathFactory) -> tuple[Spec, Path, Outcome, list[str]]:
    """PEBBLE and S-EPOA x 2 seeds (the S-EPOA runs share one snapshot), run to the end."""
    tmp = tmp_path_factory.mktemp("experiment")
    spec_path = write(tmp, TINY.format(steps=600, seeds="[0, 1]") + """
[variants.PEBBLE]
algo = "pebble"
[variants.S-EPOA]
algo = "sepoa"
""")
    spec = load_spec(spec_path)
    lines, echo = _lines()
    outcome = run_spec(spec, tmp / "results", parallel=2, echo=echo)
    return spec, tmp / "results", outcome, lines


@pytest.mark.slow
def test_the_runner_trains_the_grid_and_shares_one_snapshot(finished) -> None:
    spec, results, outcome, lines = finished
    assert outcome.exit_code == 0, "\n".join(lines)
    assert len(outcome.finished) == 4 and not outcome.failed
    assert (results / "tiny" / "spec.toml").read_text() == spec.source
    snapshots = sorted((results / "snapshots").glob("*.pt"))
    assert len(snapshots) == 1 and len(outcome.pretrained) == 1
    for run in spec.runs():
        folder = results / "tiny" / run.dir
        assert json.loads((folder / "done.json").read_text())["step"] == 600
        assert (folder / "eval.csv").read_text().splitlines()[-1].startswith("600,")
        assert (folder / "log.txt").read_text().startswith("=== ")
        config = json.loads((folder / "config.json").read_text())
        if run.algo == "sepoa":
            assert config["skill"]["snapshot"] == str(snapshots[0])
    table = status_table(spec, results)
    assert "4 runs: 4 done, 0 partial, 0 failed, 0 not started" in table


@pytest.mark.slow
def test_running_again_skips_finished_runs(finished) -> None:
    spec, results, _, _ = finished
    done = sorted((results / "tiny").rglob("done.json"))
    stamps = [p.stat().st_mtime_ns for p in done]
    lines, echo = _lines()
    outcome = run_spec(spec, results, parallel=2, echo=echo)
    assert outcome.exit_code == 0
    assert (outcome.started, outcome.resumed, outcome.pretrained) == ([], [], [])
    assert len(outcome.skipped) == 4
    assert [p.stat().st_mtime_ns for p in done] == stamps
    # The same spec under a different definition is refused, not mixed in.
    changed = write(results.parent, spec.source.replace("eval_every = 200", "eval_every = 300"),
                    "changed.toml")
    with pytest.raises(SpecError, match="different definition for 4 run"):
        run_spec(load_spec(changed, check=False), results, echo=echo)


@pytest.mark.slow
def test_a_dry_run_prints_the_plan_and_starts_nothing(tmp_path: Path) -> None:
    spec_path = write(tmp_path, TINY.format(steps=600, seeds="[0]")
                      + '[variants.S-EPOA]\nalgo = "sepoa"\n')
    lines, echo = _lines()
    outcome = run_spec(load_spec(spec_path), tmp_path / "results", dry_run=True, echo=echo)
    assert outcome.exit_code == 0
    text = "\n".join(lines)
    assert "pretrain dmc-cheetah_run-aps-200-s0-" in text and " trainer.cli pretrain " in text
    assert "start    dmc-cheetah_run/S-EPOA/eps0.3/s0" in text and "--skill.snapshot=" in text
    assert not (tmp_path / "results").exists()


def test_threads_on_the_command_line_override_the_spec_s(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from trainer.cli import main

    spec_path = write(tmp_path, TINY.replace("seeds = {seeds}", "seeds = {seeds}\nthreads = 2")
                      .format(steps=600, seeds="[0]") + '[variants.S-EPOA]\nalgo = "sepoa"\n')
    command = ["experiment", "run", str(spec_path), "--results", str(tmp_path / "results"),
               "--dry-run", "--parallel", "1"]

    def plan(*flags: str) -> tuple[list[str], str]:
        assert main(command + list(flags)) == 0
        lines = capsys.readouterr().out.splitlines()
        return [line for line in lines if "trainer.cli" in line], lines[-1]

    argvs, summary = plan("--threads", "3")
    assert len(argvs) == 2  # the snapshot's pretraining and the run
    assert all(" --threads=3 " in argv and "--threads=2" not in argv for argv in argvs)
    assert summary.endswith("1 at a time, 3 thread(s) each (--threads)")
    argvs, summary = plan()
    assert all(" --threads=2 " in argv for argv in argvs)
    assert summary.endswith("2 thread(s) each (the spec's threads)")
    assert main(command + ["--threads", "0"]) == 2
    assert capsys.readouterr().err == "error: --threads must be at least 1\n"
    assert not (tmp_path / "results").exists()


@pytest.mark.slow
def test_a_failing_run_is_reported_and_the_others_finish(tmp_path: Path) -> None:
    broken = tmp_path / "not-a-snapshot.pt"
    broken.write_text("not a snapshot")
    spec_path = write(tmp_path, TINY.format(steps=400, seeds="[0]") + f"""
[variants.SAC]
algo = "sac"
[variants.broken]
algo = "sepoa"
"skill.snapshot" = "{broken}"
""")
    lines, echo = _lines()
    outcome = run_spec(load_spec(spec_path), tmp_path / "results", parallel=2, echo=echo)
    text = "\n".join(lines)
    assert outcome.exit_code == 1
    assert outcome.failed == ["dmc-cheetah_run/broken/eps0.3/s0"]
    assert outcome.finished == ["dmc-cheetah_run/SAC/eps0.3/s0"]
    assert "FAILED   dmc-cheetah_run/broken/eps0.3/s0 exit code 2" in text
    assert "is not a readable skill snapshot" in text  # the tail of its log
    folder = tmp_path / "results" / "tiny" / "dmc-cheetah_run"
    assert (folder / "broken/eps0.3/s0/failed.json").exists()
    assert (folder / "SAC/eps0.3/s0/done.json").exists()
    table = status_table(load_spec(spec_path, check=False), tmp_path / "results")
    assert re.search(r"broken\s+0.3\s+-\s+0\s+failed", table)


@pytest.mark.slow
def test_a_killed_runner_stops_its_runs_and_the_next_call_resumes_them(tmp_path: Path) -> None:
    spec_path = write(tmp_path, TINY.format(steps=1000, seeds="[0]")
                      + '[variants.PEBBLE]\nalgo = "pebble"\n')
    results = tmp_path / "results"
    folder = results / "tiny" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s0"
    proc = subprocess.Popen(
        [sys.executable, "-m", "trainer.cli", "experiment", "run", str(spec_path),
         "--results", str(results), "--parallel", "1"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 60
    while not (folder / "checkpoint.pt").exists() and time.time() < deadline:
        time.sleep(0.1)
    assert (folder / "checkpoint.pt").exists()
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, out
    child = int(re.search(r"started\s+\S+ \(pid (\d+)\)", out).group(1))
    with pytest.raises(ProcessLookupError):
        os.kill(child, 0)  # stopped and reaped by the runner
    assert "stopped   dmc-cheetah_run/PEBBLE/eps0.3/s0" in out
    assert not (folder / "done.json").exists()

    lines, echo = _lines()
    outcome = run_spec(load_spec(spec_path), results, parallel=1, echo=echo)
    assert outcome.resumed == ["dmc-cheetah_run/PEBBLE/eps0.3/s0"] and outcome.exit_code == 0
    assert json.loads((folder / "done.json").read_text())["step"] == 1000
    log = (folder / "log.txt").read_text()
    assert log.count("\n=== ") + log.startswith("=== ") == 2 and " --resume " in log
    steps = [int(line.split(",")[0]) for line in
             (folder / "episodes.csv").read_text().splitlines()[1:]]
    assert steps == sorted(set(steps)) and steps[-1] == 1000

"""A stop rule in wall time (`stop_after_hours`): once the grid's workers have trained that long
over its sessions, no seed starts; the seeds already started finish every arm."""

from __future__ import annotations

import json
import time
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import pytest

from experiments.launch import default_database, run_experiment
from experiments.progress import seeds_before_stop
from experiments.queue import grid_key, spec_rows, stop_forecast
from experiments.sessions import FILE as SESSIONS
from experiments.spec import SpecError, load_spec
from experiments.stop_rule import FILE, apply_stop_rule, stop_rule, stop_rule_watch
from labelqueue import RunStatus, make_engine, session_factory
from sepoa.cli import main

SPEC = """
name = "ruled"
preset = "tiny"
steps = 1000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1, 2]
stop_after_hours = 2

[variants.A]
algo = "sac"

[variants.B]
algo = "pebble"
"""


def sessions_worked(folder: Path, hours: float) -> None:
    """One ended session of `hours` (experiments.sessions' file)."""
    folder.mkdir(parents=True, exist_ok=True)
    minutes = round(hours * 60)
    (folder / SESSIONS).write_text(
        "started_at,ended_at,workers,threads,ended_by\n"
        f"2026-11-28T00:00:00+00:00,2026-11-28T{minutes // 60:02d}:{minutes % 60:02d}:00+00:00,"
        "2,1,signal 15\n")


@pytest.fixture
def grid(tmp_path: Path):  # type: ignore[no-untyped-def]
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    engine = make_engine(default_database(results))
    yield spec_path, spec, results, session_factory(engine)
    engine.dispose()


def statuses(spec, sessions) -> dict[tuple[str, int], str]:  # type: ignore[no-untyped-def]
    rows = spec_rows(spec, sessions)
    return {(run.variant, run.seed): str(rows[grid_key(spec, run)].status)
            for run in spec.runs()}


def test_before_the_hours_are_spent_nothing_is_stopped(  # type: ignore[no-untyped-def]
        grid, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path, spec, results, sessions = grid
    sessions_worked(results / "ruled", 1.5)
    rule = apply_stop_rule(spec, sessions, results, echo=lambda line: None)
    assert rule is not None and not rule.reached
    assert set(statuses(spec, sessions).values()) == {"queued"}
    assert not (results / "ruled" / FILE).exists()
    assert rule.text(lambda s: f"{s / 3600:g} h") == (
        "stop rule: no seed starts after 2 h of the workers' training; 1.5 h spent")
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    assert capsys.readouterr().out.splitlines()[-2:] == [
        "stop rule: no seed starts after 2 h of the workers' training; 1h30m spent",
        "forecast: none while no worker trains"]


def test_the_forecast_replays_the_queue_on_the_workers_as_they_come_free() -> None:
    hour = 3600.0
    # 1 h worked of 3; two workers hold runs with 0.5 h and 1 h left; the queue: seed 1's
    # second run (1 h; seed 1 started), then seeds 2, 3, 4 (two 1 h runs each).
    queued = [(1, hour)] + [(seed, hour) for seed in (2, 3, 4) for _ in range(2)]
    said = seeds_before_stop(3, 1 * hour, 2, [0.5 * hour, hour], queued, started={1})
    # Seed 1's run at 1.5 h, seed 2 at 2 h and 2.5 h, seed 3's first claim at 3 h: left out,
    # and seed 4 after it.
    assert said == ("forecast, 2 worker(s), these estimates: of the seeds not started, 2 "
                    "starts before the stop rule's 3 h (the last, 2, at about 2h00m); 3-4 left "
                    "out (seed 3 would start at about 3h00m)")
    assert seeds_before_stop(10, 0, 2, [], queued, started={1}).endswith(
        "2-4 start before the stop rule's 10 h (the last, 4, at about 2h00m); none is left out")
    assert seeds_before_stop(3, 3.5 * hour, 1, [hour], [(5, hour)], started=()).endswith(
        "none starts before the stop rule's 3 h; 5 left out (seed 5 would start at about 4h30m)")
    assert seeds_before_stop(3, hour, 1, [hour], [(1, hour)], started={1}) == (
        "forecast: no queued run of a seed not started")


def test_spent_hours_stop_the_seeds_not_started_and_the_started_ones_finish(
        grid, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    spec_path, spec, results, sessions = grid
    sessions_worked(results / "ruled", 2.5)
    started = next(run for run in spec.runs() if run.variant == "B" and run.seed == 0)
    (results / grid_key(spec, started)).mkdir(parents=True)  # a worker took seed 0's B run
    said: list[str] = []
    rule = apply_stop_rule(spec, sessions, results, echo=said.append)
    assert rule is not None and rule.seeds_not_started == (1, 2)
    assert statuses(spec, sessions) == {
        ("A", 0): "queued", ("B", 0): "queued",  # seed 0 started: both arms go on
        ("A", 1): "stopped", ("B", 1): "stopped", ("A", 2): "stopped", ("B", 2): "stopped"}
    assert said == ["ruled: the stop rule's 2 h are spent: 4 queued run(s) of seeds not "
                    "started stopped (1, 2)"]
    record = json.loads((results / "ruled" / FILE).read_text())
    assert record["seeds_not_started"] == [1, 2] and record["worked_s"] == 9000

    # Running the spec again queues the stopped runs again; its launcher stops them again
    # before any worker starts, and the seeds left out stay those of the first time.
    seen: list[dict[tuple[str, int], str]] = []

    def train(url, results, workers, threads, echo):  # type: ignore[no-untyped-def]
        seen.append(statuses(spec, sessions))
        return None

    run_experiment(spec, results=results, workers=1, echo=lambda line: None, train=train)
    assert seen[0][("A", 1)] == "stopped" and seen[0][("A", 0)] == "queued"
    rule = stop_rule(spec, sessions, results)
    assert rule is not None and rule.recorded and rule.seeds_not_started == (1, 2)

    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    lines = capsys.readouterr().out.splitlines()
    last = lines[-1]
    assert last.startswith("stop rule: no seed starts after 2 h of the workers' training; "
                           "reached (") and last.endswith("seeds not started: 1, 2")
    # The runs left out will not train: no time left is counted for them.
    rows = {(line.split()[1], line.split()[4]): line for line in lines[2:8]}
    assert [key for key, line in rows.items() if line.endswith(" left out")] == [
        ("A", "1"), ("A", "2"), ("B", "1"), ("B", "2")]
    assert lines[8] == ("time left (estimated): 2 run(s) without an estimate yet (no run of "
                        "their task and variant has logged an episode); not counted: 4 run(s) "
                        "of seeds the stop rule left out, which will not train")


@pytest.mark.parametrize("hours", ["0", "-1", "true", '"ten"'])
def test_stop_after_hours_takes_a_positive_number(tmp_path: Path, hours: str) -> None:
    path = tmp_path / "spec.toml"
    path.write_text(SPEC.replace("stop_after_hours = 2", f"stop_after_hours = {hours}"))
    with pytest.raises(SpecError, match="'stop_after_hours' takes a number of hours above 0"):
        load_spec(path)


def test_the_launchers_watch_outlives_a_failed_check(grid) -> None:  # type: ignore[no-untyped-def]
    _, spec, results, sessions = grid
    sessions_worked(results / "ruled", 2.5)
    blocked = results / "ruled" / FILE
    blocked.mkdir()  # the record cannot be written: the check fails
    said: list[str] = []

    def wait_for(condition) -> None:  # type: ignore[no-untyped-def]
        deadline = time.monotonic() + 10
        while not condition():
            assert time.monotonic() < deadline, said
            time.sleep(0.02)

    with stop_rule_watch(spec, sessions, results, echo=said.append, every_s=0.05):
        wait_for(lambda: any("could not be checked" in line for line in said))
        blocked.rmdir()
        wait_for(lambda: (results / "ruled" / FILE).is_file())
    assert said[0].startswith("ruled: the stop rule could not be checked (IsADirectoryError: ")
    assert said[0].endswith("checking again in 0.05 s")
    assert set(statuses(spec, sessions).values()) == {"stopped"}  # no seed had started


def test_the_forecast_counts_only_live_workers_and_gives_a_dead_ones_run_to_them(
        tmp_path: Path) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec = load_spec(spec_path)
    hour = 3600.0
    runs = sorted(spec.runs(), key=lambda run: (run.seed, run.variant))  # queued seed first
    created = datetime(2026, 11, 28, 8, 0)
    rows = {grid_key(spec, run): SimpleNamespace(
        id=i, created_at=created, status=RunStatus.QUEUED, worker_id=None)
        for i, run in enumerate(runs)}
    live, dead = (rows[grid_key(spec, runs[i])] for i in (0, 1))  # seed 0's A and B
    live.status, live.worker_id = RunStatus.RUNNING, "w1"
    dead.status, dead.worker_id = RunStatus.RUNNING, "w2"  # silent: taken over when free
    left = dict.fromkeys(rows, hour)
    said = stop_forecast(spec, rows, tmp_path, left, {"w1"}, 0.0)  # type: ignore[arg-type]
    # One live worker: its run till 1 h, then the dead worker's till 2 h; seed 1 would start at
    # 2 h, the rule's hours. (Counting the dead worker's run as a second worker would start
    # seed 1 at 1 h.)
    assert said == ("forecast, 1 worker(s), these estimates: of the seeds not started, none "
                    "starts before the stop rule's 2 h; 1-2 left out (seed 1 would start at "
                    "about 2h00m)")


def test_enqueueing_without_local_workers_keeps_the_left_out_seeds_stopped(
        grid) -> None:  # type: ignore[no-untyped-def]
    _, spec, results, sessions = grid
    sessions_worked(results / "ruled", 2.5)
    started = next(run for run in spec.runs() if run.variant == "A" and run.seed == 0)
    (results / grid_key(spec, started)).mkdir(parents=True)
    apply_stop_rule(spec, sessions, results, echo=lambda line: None)
    ruled = statuses(spec, sessions)
    said: list[str] = []
    # The Slurm enqueue step, or `run --no-workers`: workers elsewhere claim at once.
    assert run_experiment(spec, results=results, workers=0, echo=said.append) == 0
    assert statuses(spec, sessions) == ruled
    assert "0 queued again" in said[0] and "4 left out by the stop rule (stopped)" in said[0]


def test_spent_hours_found_without_local_workers_stop_the_seeds_not_started(
        grid) -> None:  # type: ignore[no-untyped-def]
    _, spec, results, sessions = grid
    sessions_worked(results / "ruled", 2.5)
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    assert set(statuses(spec, sessions).values()) == {"stopped"}
    assert json.loads((results / "ruled" / FILE).read_text())["seeds_not_started"] == [0, 1, 2]


def test_a_part_launched_alone_keeps_the_whole_grids_rule(
        grid) -> None:  # type: ignore[no-untyped-def]
    _, spec, results, sessions = grid
    sessions_worked(results / "ruled", 2.5)
    started = next(run for run in spec.runs() if run.variant == "A" and run.seed == 1)
    (results / grid_key(spec, started)).mkdir(parents=True)  # seed 1 started in part A
    part = spec.only(["B"], [0, 1])  # `--variant B --seed 0 --seed 1`
    rule = apply_stop_rule(part, sessions, results, echo=lambda line: None)
    assert rule is not None and rule.seeds_not_started == (0, 2)
    assert json.loads((results / "ruled" / FILE).read_text())["seeds_not_started"] == [0, 2]
    assert statuses(spec, sessions) == {
        ("A", 0): "stopped", ("B", 0): "stopped", ("A", 1): "queued", ("B", 1): "queued",
        ("A", 2): "stopped", ("B", 2): "stopped"}
    rule = stop_rule(spec, sessions, results)
    assert rule is not None and rule.recorded and rule.seeds_not_started == (0, 2)

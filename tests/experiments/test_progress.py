"""How long a grid has left: from its episodes.csv files, the finished runs of each task and
variant first (their clocks from the step reached on, else their rates), and one line for the
grid in `sepoa experiment status`."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from sqlalchemy import update

from experiments import progress
from experiments.launch import default_database, run_experiment
from experiments.progress import (
    reward_epochs,
    seconds_after,
    seconds_left,
    summary,
    training_clock,
    training_rate,
)
from experiments.queue import grid_key
from experiments.spec import load_spec
from labelqueue import Run, RunStatus, make_engine, session_factory
from sepoa.cli import main
from trainer import round_progress
from trainer.reward_model import TrainingProgress

SPEC = """
name = "eta"
preset = "tiny"
steps = 1000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1, 2]

[variants.PEBBLE]
algo = "pebble"

[variants.SAC]
algo = "sac"
"""


def write_episodes(folder: Path, rows: list[dict[str, object]], cut: str = "") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / "episodes.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
        f.write(cut)


def test_a_runs_rate_is_its_steps_over_its_phase_clock_seconds(tmp_path: Path) -> None:
    # 1000 steps in 10 s, then 1000 in 30 s (a feedback round): 2000 / 40 = 50 steps/s; the
    # fps column (since the process started) is not what counts when seconds are there.
    write_episodes(tmp_path, [{"step": 1000, "fps": 900.0, "seconds_total": 10.0},
                              {"step": 2000, "fps": 900.0, "seconds_total": 30.0}],
                   cut="3000,90")  # the row being appended, cut short
    assert training_rate(tmp_path) == pytest.approx(50.0)


def test_without_phase_clock_columns_the_last_rows_fps_is_the_rate(tmp_path: Path) -> None:
    write_episodes(tmp_path, [{"step": 1000, "fps": 80.0}, {"step": 2000, "fps": 60.0}])
    assert training_rate(tmp_path) == 60.0
    assert training_rate(tmp_path / "not-started") is None


def test_time_left_prefers_finished_runs_then_the_runs_own_rate() -> None:
    left = seconds_left([
        # A variant with finished runs: their median rate for every unfinished one.
        ("g/A/s0", 1000, 1000, True, 10.0, None),
        ("g/A/s1", 1000, 1000, True, 30.0, None),
        ("g/A/s2", 1000, 1000, True, 20.0, None),
        ("g/A/s3", 1000, 400, False, 100.0, None),  # its early steps were fast: not what counts
        ("g/A/s4", 1000, 0, False, None, None),
        # None finished: a started run's own rate, and queued ones at the started runs' median.
        ("g/B/s0", 1000, 500, False, 5.0, None),
        ("g/B/s1", 1000, 0, False, None, None),
        # None started: no estimate.
        ("g/C/s0", 1000, 0, False, None, None),
    ])
    assert left == {"g/A/s0": 0.0, "g/A/s1": 0.0, "g/A/s2": 0.0, "g/A/s3": 30.0,
                    "g/A/s4": 50.0, "g/B/s0": 100.0, "g/B/s1": 200.0, "g/C/s0": None}
    assert left.by_rate == {"g/A/s3", "g/A/s4", "g/B/s0", "g/B/s1"}
    assert summary(left, workers=2, by_rate=len(left.by_rate)) == (
        "time left (estimated): 6m20s of training over 4 run(s), about 3m20s with the 2 "
        "worker(s) training now; 1 run(s) without an estimate yet (no run of their task and "
        "variant has logged an episode); 4 of them from average rates (no finished run of "
        "their variant has the phase clock): likely short, as late steps hold the largest "
        "feedback rounds")
    # One long run bounds the wall time, however many workers there are.
    assert summary({"a": 3600.0, "b": 60.0}, workers=8) == (
        "time left (estimated): 1h01m of training over 2 run(s), about 1h00m with the 8 "
        "worker(s) training now")
    assert summary({"a": 0.0}, workers=0) == "time left: none, every run is done"


def test_status_gives_each_run_and_the_grid_its_time_left(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    pebble = results / "eta" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3"
    for seed, seconds in ((0, 100.0), (1, 25.0)):  # finished, at 10 and 40 steps/s
        write_episodes(pebble / f"s{seed}", [{"step": 1000, "fps": 1.0,
                                              "seconds_total": seconds}])
        (pebble / f"s{seed}" / "done.json").write_text("{}")
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split()[-1] == "left"
    left = {tuple(line.split()[1:5:3]): line.split()[-1] for line in lines[2:8]}
    # The queued seed: the median of the finished runs' whole clocks, 100 s and 25 s.
    assert left == {("PEBBLE", "0"): "-", ("PEBBLE", "1"): "-", ("PEBBLE", "2"): "1m02s",
                    ("SAC", "0"): "?", ("SAC", "1"): "?", ("SAC", "2"): "?"}
    assert lines[8] == (
        "time left (estimated): 1m02s of training over 1 run(s); 3 run(s) without an estimate "
        "yet (no run of their task and variant has logged an episode)")


def test_a_runs_clock_adds_up_its_phase_clock_seconds(tmp_path: Path) -> None:
    write_episodes(tmp_path, [{"step": 500, "fps": 9.0, "seconds_total": 10.0},
                              {"step": 1000, "fps": 9.0, "seconds_total": 90.0}],
                   cut="1500,90")
    assert training_clock(tmp_path) == [(500, 10.0), (1000, 100.0)]
    # Rows from before the phase clock: no clock, whatever later rows carry.
    write_episodes(tmp_path, [{"step": 500, "fps": 9.0, "seconds_total": ""},
                              {"step": 1000, "fps": 9.0, "seconds_total": 90.0}])
    assert training_clock(tmp_path) is None
    write_episodes(tmp_path, [{"step": 500, "fps": 9.0}])
    assert training_clock(tmp_path) is None
    assert training_clock(tmp_path / "not-started") is None


def test_the_time_after_a_step_is_read_off_the_clock_between_rows() -> None:
    clock = [(500, 10.0), (1000, 100.0)]
    assert seconds_after(clock, 0) == 100.0
    assert seconds_after(clock, 250) == 95.0
    assert seconds_after(clock, 500) == 90.0
    assert seconds_after(clock, 750) == 45.0
    assert seconds_after(clock, 1000) == 0.0
    assert seconds_after(clock, 1200) == 0.0


def test_finished_runs_clocks_charge_the_late_costly_steps() -> None:
    # Two finished runs whose second half (its feedback rounds) took 9x their first half.
    late_rounds = [(500, 10.0), (1000, 100.0)]
    slower = [(500, 20.0), (1000, 200.0)]
    left = seconds_left([
        ("g/A/s0", 1000, 1000, True, 10.0, late_rounds),
        ("g/A/s1", 1000, 1000, True, 5.0, slower),
        ("g/A/s2", 1000, 500, False, 50.0, None),
        ("g/A/s3", 1000, 0, False, None, None),
        # A finished run without a clock leaves its group to the rates.
        ("g/B/s0", 1000, 1000, True, 10.0, None),
        ("g/B/s1", 1000, 500, False, 50.0, None),
    ])
    # At 500 steps: the median of 90 s and 180 s, where the finished runs' median rate
    # (7.5 steps/s) would say 67 s.
    assert left == {"g/A/s0": 0.0, "g/A/s1": 0.0, "g/A/s2": 135.0, "g/A/s3": 150.0,
                    "g/B/s0": 0.0, "g/B/s1": 50.0}
    assert left.by_rate == {"g/B/s1"}


def test_status_shows_the_reward_epoch_a_rounds_training_has_saved(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A long round holds a run's step still for as long as it trains: status says how far
    that training has got, from the file the trainer saves it in."""
    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    folder = results / "eta" / "dmc-cheetah_run" / "PEBBLE" / "eps0.3" / "s1"
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"reward": {"max_epochs": 50}}))
    assert reward_epochs(folder) is None  # no round training
    saved = round_progress.RoundProgress(str(folder / progress.ROUND_PROGRESS))
    saved.save("round 7", {"training": TrainingProgress(epochs=23, loss=0.4, accuracy=0.8)})
    assert reward_epochs(folder) == (23, 50)

    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    lines = capsys.readouterr().out.splitlines()
    row = next(line for line in lines if line.split()[1:5:3] == ["PEBBLE", "1"])
    assert "started, round: reward epoch 23/50" in row

    (folder / progress.ROUND_PROGRESS).write_bytes(b"cut short")  # caught being replaced
    assert reward_epochs(folder) is None
    assert progress.ROUND_PROGRESS == round_progress.ROUND_PROGRESS


def write_pretraining(path: Path, rows: list[tuple[int, float]]) -> None:
    """A pretraining's metrics file beside its snapshot: (step, fps) rows."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.with_suffix(".csv").open("w", newline="") as f:
        f.write("step,episode,return,fps\n")
        f.writelines(f"{step},{i + 1},0.0,{fps}\n" for i, (step, fps) in enumerate(rows))


def test_a_snapshot_still_to_pretrain_is_waited_for_once_at_its_rate(tmp_path: Path) -> None:
    from runvocab.config import build_config
    from runvocab.snapshot_names import intermediate_path, snapshot_path

    def sepoa(seed: int, **more: object) -> object:
        return build_config("dmc:cheetah_run", "tiny", {
            "algo": "sepoa", "seed": seed, "skill.pretrain_steps": 1000,
            "skill.snapshot_dir": str(tmp_path)} | more)

    cfgs = {seed: sepoa(seed) for seed in range(5)}
    path = {seed: Path(snapshot_path(cfg)) for seed, cfg in cfgs.items()}  # type: ignore[arg-type]
    path[0].write_bytes(b"snapshot")  # seed 0: pretrained
    write_pretraining(path[1], [(100, 50.0), (400, 20.0)])  # seed 1: at 400, 20 steps/s
    write_pretraining(path[4], [(1000, 10.0)])  # seed 4: its csv is a finished run's, at 10/s
    path[4].write_bytes(b"snapshot")
    # Seed 3: a longer pretraining of the seed wrote a snapshot at this length on its way.
    longer = Path(str(path[3]).replace("-1000-", "-5000-"))
    Path(intermediate_path(str(longer), 1000)).write_bytes(b"snapshot")
    runs = [("sac", build_config("dmc:cheetah_run", "tiny", {"algo": "sac"})),
            ("none", sepoa(7, **{"skill.pretrain_steps": 0}))]
    runs += [(f"s{seed}", cfg) for seed, cfg in cfgs.items()]
    runs += [("s1 again", sepoa(1, **{"skill.task_skill_draw": "refit"}))]  # same snapshot
    left = progress.pretraining_left(runs)  # type: ignore[arg-type]
    assert left == {"sac": 0.0, "none": 0.0, "s0": 0.0, "s1": 600 / 20.0, "s1 again": 0.0,
                    "s2": 1000 / median_of([20.0, 10.0]), "s3": 0.0, "s4": 0.0}
    # No pretraining of the task and backend to go by: unknown.
    empty = tmp_path / "elsewhere"
    alone = sepoa(9, **{"skill.snapshot_dir": str(empty)})
    assert progress.pretraining_left([("s9", alone)]) == {"s9": None}  # type: ignore[list-item]


def median_of(rates: list[float]) -> float:
    """The median of the other pretrainings' final rates (seed 2 has none of its own)."""
    import statistics
    return statistics.median(rates)


def test_status_adds_a_missing_snapshots_pretraining_to_the_first_run_needing_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from runvocab.snapshot_names import snapshot_path

    spec_path = tmp_path / "spec.toml"
    spec_path.write_text(SEPOA_SPEC)
    spec, results = load_spec(spec_path), tmp_path / "results"
    assert run_experiment(spec, results=results, workers=0, echo=lambda line: None) == 0
    runs = {(run.variant, run.seed): run for run in spec.runs()}
    folder = results / "pre" / "dmc-cheetah_run"
    done = folder / "A" / "eps0.3" / "s0"  # finished in 100 s of training
    write_episodes(done, [{"step": 1000, "fps": 1.0, "seconds_total": 100.0}])
    (done / "done.json").write_text("{}")
    # The grid's workers keep snapshots in <results>/snapshots: seed 1's is half pretrained,
    # at 10 steps/s.
    seed1 = Path(snapshot_path(apply_snapshot_dir(runs[("A", 1)].config(), results)))
    write_pretraining(seed1, [(1000, 10.0)])
    # A worker holds A s1, pretraining (its heartbeat's progress).
    engine = make_engine(default_database(results))
    with session_factory(engine)() as session, session.begin():
        session.execute(update(Run).where(Run.grid_key == grid_key(spec, runs[("A", 1)]))
                        .values(status=RunStatus.RUNNING, worker_id="w1", step=0,
                                progress={"pretraining_step": 1000, "pretraining_steps": 2000}))
    engine.dispose()
    assert main(["experiment", "status", str(spec_path), "--results", str(results)]) == 0
    lines = capsys.readouterr().out.splitlines()
    left = {tuple(line.split()[1:5:3]): line.split()[-1] for line in lines[2:6]}
    # A s1: 100 s of training after 1000 pretraining steps to go at 10/s; B s1 shares the
    # snapshot (only the online draw of z_task differs): its training alone.
    assert left == {("A", "0"): "-", ("A", "1"): "3m20s", ("B", "0"): "?", ("B", "1"): "?"}
    assert "-, pretraining 1000/2000" in next(line for line in lines if " A " in line
                                               and "running" in line)


def apply_snapshot_dir(cfg: object, results: Path) -> object:
    from runvocab.config import apply_overrides
    return apply_overrides(cfg, {"skill.snapshot_dir": str(results / "snapshots")})  # type: ignore[arg-type]


SEPOA_SPEC = """
name = "pre"
preset = "tiny"
steps = 1000
tasks = ["dmc:cheetah_run"]
eps = [0.3]
seeds = [0, 1]

[overrides]
"skill.pretrain_steps" = 2000

[variants.A]
algo = "sepoa"

[variants.B]
algo = "sepoa"
"skill.task_skill_draw" = "refit"
"""

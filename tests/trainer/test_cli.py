"""The `sepoa` command as a user runs it: a subprocess on a tiny config, a kill, a resume."""

import csv
import json
import os
import signal
import subprocess
import sys
import time

import pytest

SEPOA = [sys.executable, "-m", "sepoa"]
TINY = ["train", "--task", "dmc:cheetah_run", "--algo", "pebble", "--teacher", "noisy",
        "--eps", "0.3", "--preset", "tiny", "--seed", "3", "--threads", "1", "--no-progress",
        "--update_every", "4"]  # a SAC update every 4 steps: the updates are most of the time


def _run(args: list[str], **kw) -> subprocess.CompletedProcess:
    return subprocess.run(SEPOA + args, capture_output=True, text=True, timeout=300, **kw)


def _in_process(args: list[str], capsys) -> subprocess.CompletedProcess:
    """`sepoa` run by its main() in this interpreter, with the exit status and stderr a process
    would have (a SystemExit with a message exits 1 and prints it)."""
    from sepoa.cli import main

    try:
        code = main(args)
    except SystemExit as exited:
        code = 1 if isinstance(exited.code, str) else int(exited.code or 0)
        if isinstance(exited.code, str):
            print(exited.code, file=sys.stderr)
    captured = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, captured.out, captured.err)


def _rows(path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _labels(run_dir) -> list[dict]:
    with open(os.path.join(run_dir, "labels.jsonl")) as f:
        rows = [json.loads(line) for line in f]
    for row in rows:
        row.pop("answered_at")
    return rows


def test_cli_smoke_run_uses_labels_and_writes_metrics(tmp_path):
    run_dir = tmp_path / "run"
    out = _run(TINY + ["--steps", "1200", "--run-dir", str(run_dir), "--eval_every", "600"])
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    # rounds at 400 and 800; none at the last step, where labels could no longer be used
    assert summary["step"] == 1200 and summary["labels_used"] == 20
    assert len(_labels(run_dir)) == 20
    rounds = _rows(run_dir / "rounds.csv")
    assert len(rounds) == 2
    assert all(0.0 <= float(r["distinguishable_ratio"]) <= 1.0 for r in rounds)
    assert len(_rows(run_dir / "episodes.csv")) == 6
    assert [int(r["step"]) for r in _rows(run_dir / "eval.csv")] == [600, 1200]
    assert os.listdir(run_dir / "tb")
    config = json.loads((run_dir / "config.json").read_text())
    assert config["teacher"]["eps"] == 0.3 and config["sac"]["hidden_dim"] == 32


def test_cli_rejects_bad_input_with_a_clear_message(tmp_path, capsys):
    out = _in_process(TINY + ["--task", "dmc:cheetah_fly", "--run-dir", str(tmp_path / "a")],
                      capsys)
    assert out.returncode == 2 and "cheetah_fly" in out.stderr and "dmc:cheetah_run" in out.stderr
    out = _in_process(TINY + ["--algo", "dqn", "--run-dir", str(tmp_path / "b")], capsys)
    assert out.returncode == 2 and "dqn" in out.stderr and "pebble" in out.stderr
    out = _in_process(["train", "--resume", "--run-dir", str(tmp_path / "nothing")], capsys)
    assert out.returncode != 0 and "holds no run" in out.stderr


def _wait_for_rounds(run_dir, n: int, proc: subprocess.Popen, timeout: float = 240) -> None:
    deadline = time.time() + timeout
    path = run_dir / "rounds.csv"
    while time.time() < deadline:
        if path.exists() and len(_rows(path)) >= n:
            return
        if proc.poll() is not None:
            pytest.fail(f"run ended before round {n}: {proc.stderr.read()}")
        time.sleep(0.05)
    pytest.fail(f"no round {n} within {timeout} s")


def test_resume_after_sigkill_continues_identically_and_loses_no_label(tmp_path, capsys):
    steps = ["--steps", "1600"]
    reference = tmp_path / "reference"  # never killed: it needs no process of its own
    out = _in_process(TINY + steps + ["--run-dir", str(reference)], capsys)
    assert out.returncode == 0, out.stderr

    killed = tmp_path / "killed"
    proc = subprocess.Popen(SEPOA + TINY + steps + ["--run-dir", str(killed)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_rounds(killed, 2, proc)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    labels_at_kill = _labels(killed)
    assert 20 <= len(labels_at_kill) < 40

    out = _run(["train", "--run-dir", str(killed), "--resume", "--no-progress"])
    assert out.returncode == 0, out.stderr
    resumed = _labels(killed)
    # every label given before the kill is still there, none twice, and the run went on
    assert resumed[: len(labels_at_kill)] == labels_at_kill
    assert len({r["query_id"] for r in resumed}) == len(resumed) == 30
    # same replay buffer, labels and random state: the same labels and returns as a run that
    # was never killed
    assert resumed == _labels(reference)
    ref_eps, res_eps = _rows(reference / "episodes.csv"), _rows(killed / "episodes.csv")
    assert [r["step"] for r in res_eps] == [r["step"] for r in ref_eps]
    assert [float(r["return"]) for r in res_eps] == pytest.approx(
        [float(r["return"]) for r in ref_eps], rel=1e-5)
    assert [r["reward_accuracy"] for r in _rows(killed / "rounds.csv")] == [
        r["reward_accuracy"] for r in _rows(reference / "rounds.csv")]


def test_each_baseline_is_pebble_with_its_own_piece_switched_on():
    from runvocab.config import build_config

    def cfg(algo, task="dmc:walker_run", preset="paper"):
        return build_config(task, preset, {"algo": algo})

    pebble = cfg("pebble")
    assert not (pebble.reward.surf or pebble.reward.rune or pebble.reward.rime)
    assert pebble.feedback.segment_length == 50 and pebble.unsup_steps == 9000
    surf = cfg("surf")
    assert surf.reward.surf and surf.feedback.segment_length == 60  # cropped to 45-55
    assert surf.feedback.selection == "disagreement"
    assert cfg("rune").reward.rune and cfg("rime").reward.rime
    assert cfg("rime").unsup_steps == 9000
    assert cfg("rime", "dmc:cheetah_run").unsup_steps == 2000  # RIME's own, on cheetah
    sepoa = cfg("sepoa")
    assert sepoa.feedback.selection == "skill" and sepoa.reward.surf
    # A size preset shrinks what the algorithm preset set; explicit flags win over both.
    tiny = cfg("sepoa", preset="tiny")
    assert tiny.feedback.segment_length == 20 and tiny.reward.surf_crop_max <= 20
    assert build_config("dmc:walker_run", "paper",
                        {"algo": "sepoa", "reward.surf": False}).reward.surf is False


def test_presets_prints_every_layer_in_the_order_they_apply():
    result = _run(["presets"])
    assert result.returncode == 0, result.stderr
    layers = json.loads(result.stdout)
    assert list(layers) == ["family", "task", "algorithm", "algorithm and task", "size"]
    assert layers["algorithm"]["sepoa"]["feedback.segment_length"] == 60
    assert layers["algorithm"]["sepoa"]["feedback.selection_mode"] == "per_query"
    assert layers["algorithm and task"]["rime dmc:cheetah_run"] == {"unsup_steps": 2000}
    assert layers["size"]["small"]["skill.initial_rollouts"] == 10

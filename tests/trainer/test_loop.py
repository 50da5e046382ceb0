"""The preference loop end to end on tiny configs: budget accounting and the label record."""

import csv
import json
import os

import numpy as np
import pytest

from runvocab.config import build_config
from trainer.hooks import RunHooks
from trainer.loop import TrainingRun


def _rows(path: str) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _labels(run_dir: str) -> list[dict]:
    with open(os.path.join(run_dir, "labels.jsonl")) as f:
        return [json.loads(line) for line in f]


def test_budget_counts_every_label_including_the_first_round(tmp_path):
    # Rounds at 400 (first: uniform), 800, 1200; 10 per round; budget 25 -> 10 + 10 + 5.
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "steps": 1600, "threads": 1, "run_dir": str(tmp_path),
        "feedback.budget": 25, "teacher.eps": 0.3,
        "update_every": 4,  # fewer SAC updates (most of a tiny run's time), the same rounds
    })
    summary = TrainingRun(cfg, progress=False).train()
    rounds = _rows(tmp_path / "rounds.csv")
    assert [int(r["queries"]) for r in rounds] == [10, 10, 5]
    assert [int(r["labels_used"]) for r in rounds] == [10, 20, 25]
    assert [int(r["step"]) for r in rounds] == [400, 800, 1200]
    assert summary["labels_used"] == 25
    labels = _labels(str(tmp_path))
    assert len(labels) == 25 and len({lab["query_id"] for lab in labels}) == 25
    assert labels[0]["rule"] == "uniform" and labels[-1]["rule"] == "disagreement"
    # the two segments of a query always come from different trajectories
    assert all(lab["trajectory0"] != lab["trajectory1"] for lab in labels)
    # the label record agrees with the teacher's rule: a distinguishable answer follows the
    # segments' true sums
    for lab in labels:
        if lab["distinguishable"] and lab["choice"] in ("first", "second"):
            better = "second" if lab["segment_return1"] > lab["segment_return0"] else "first"
            assert lab["choice"] == better
    # each query records the R_avg it was selected under: the mean return of the 10 newest
    # episodes (200 steps each) when its round opened, which the noisy teacher's band scales
    episodes = _rows(tmp_path / "episodes.csv")
    for lab in labels:
        returns = [float(e["return"]) for e in episodes if int(e["step"]) <= lab["step"]]
        assert lab["r_avg"] == pytest.approx(sum(returns[-10:]) / len(returns[-10:]))
    # every round logs the distinguishable ratio, equal to the fraction in the label record
    for r in rounds:
        in_round = [lab for lab in labels if lab["round"] == int(r["round"])]
        ratio = sum(lab["distinguishable"] for lab in in_round) / len(in_round)
        assert float(r["distinguishable_ratio"]) == pytest.approx(ratio)


def test_sac_oracle_uses_no_labels(tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sac", "steps": 600, "threads": 1, "run_dir": str(tmp_path), "eval_every": 400,
    })
    summary = TrainingRun(cfg, progress=False).train()
    assert "labels_used" not in summary
    assert not os.path.exists(tmp_path / "labels.jsonl")
    evals = _rows(tmp_path / "eval.csv")
    assert [int(r["step"]) for r in evals] == [400]
    assert len(_rows(tmp_path / "episodes.csv")) == 3


def test_an_existing_run_directory_is_not_overwritten(tmp_path):
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sac", "steps": 200, "threads": 1, "run_dir": str(tmp_path),
    })
    TrainingRun(cfg, progress=False).train()
    before = (tmp_path / "episodes.csv").read_text()
    with pytest.raises(FileExistsError, match="--resume"):
        TrainingRun(cfg, progress=False)
    assert (tmp_path / "episodes.csv").read_text() == before


def test_pebble_on_metaworld_records_success_and_contexts(tmp_path):
    cfg = build_config("metaworld:door-open", "tiny", {
        "algo": "pebble", "steps": 1000, "threads": 1, "run_dir": str(tmp_path),
        "eval_every": 1000, "episode_length": 200, "update_every": 4,
    })
    assert cfg.sac.hidden_layers == 2 and cfg.feedback.per_round == 10  # tiny beats the family
    run = TrainingRun(cfg, progress=False)
    summary = run.train()
    assert summary["labels_used"] == 20  # rounds at 400 and 800
    evals = _rows(tmp_path / "eval.csv")
    assert len(evals) == 1 and 0.0 <= float(evals[0]["success_rate"]) <= 1.0
    episodes = _rows(tmp_path / "episodes.csv")
    assert len(episodes) == 5 and all(r["success"] in ("0.0", "1.0") for r in episodes)
    # each stored trajectory replays: restoring its first state gives its first observation
    traj = run.pool[0]
    np.testing.assert_array_equal(run.env.restore(traj.states[5], traj.context), traj.obs[5])


@pytest.mark.parametrize("override, message", [
    ({"feedback.selection": "bald"}, "feedback.selection 'bald'; valid: uniform"),
    ({"teacher.kind": "oracle"}, "teacher.kind 'oracle'; valid: noisy, bpref"),
    ({"teacher.eps": 1.5}, "teacher.eps is an error rate"),
    ({"feedback.per_round": 0}, "feedback.per_round must be positive"),
    ({"episode_length": 10}, "shorter than a segment"),
    ({"feedback.selection_mode": "best"}, "selection_mode 'best'; valid: per_query, top_k"),
    ({"feedback.compare_rule": "skill"}, "use algo sepoa"),
    ({"teacher.tie": "last"}, "teacher.tie 'last'; valid: equal, random, first"),
    ({"reset_updates": -1}, "reset_updates cannot be negative"),
    ({"algo": "sepoaa"}, "did you mean .sepoa."),
])
def test_bad_configuration_is_rejected_before_training(tmp_path, override, message):
    cfg = build_config("dmc:cheetah_run", "tiny", {"run_dir": str(tmp_path / "run")} | override)
    with pytest.raises(ValueError, match=message):
        TrainingRun(cfg, progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_stopped_between_choosing_queries_and_answering_them_resumes(tmp_path,
                                                                           monkeypatch):
    overrides = {"algo": "pebble", "steps": 1200, "threads": 1, "teacher.eps": 0.3,
                 "update_every": 4}
    reference = build_config("dmc:cheetah_run", "tiny",
                             overrides | {"run_dir": str(tmp_path / "reference")})
    TrainingRun(reference, progress=False).train()

    cfg = build_config("dmc:cheetah_run", "tiny", overrides | {"run_dir": str(tmp_path / "cut")})
    finish = TrainingRun._finish_round

    def stop_in_second_round(self, answers):
        if self.feedback.rounds == 1:
            raise KeyboardInterrupt  # the process dies with round 1's queries chosen, unanswered
        finish(self, answers)

    monkeypatch.setattr(TrainingRun, "_finish_round", stop_in_second_round)
    with pytest.raises(KeyboardInterrupt):
        TrainingRun(cfg, progress=False).train()
    assert len(_labels(cfg.run_dir)) == 10
    monkeypatch.setattr(TrainingRun, "_finish_round", finish)

    resumed = TrainingRun(cfg, resume=True, progress=False)
    assert [q.query_id for q in resumed.feedback.pending] == [f"r1-q{i}" for i in range(10)]
    resumed.train()

    def strip(rows):
        return [{k: v for k, v in r.items() if k != "answered_at"} for r in rows]

    assert strip(_labels(cfg.run_dir)) == strip(_labels(reference.run_dir))
    assert [r["reward_accuracy"] for r in _rows(os.path.join(cfg.run_dir, "rounds.csv"))] == [
        r["reward_accuracy"] for r in _rows(os.path.join(reference.run_dir, "rounds.csv"))]


def test_pebble_resets_its_critic_at_the_first_round_then_catches_up_on_r_hat(tmp_path,
                                                                            monkeypatch):
    from trainer.sac import SAC

    calls = []
    reset, update = SAC.reset_critic, SAC.update
    monkeypatch.setattr(SAC, "reset_critic", lambda self: (calls.append("reset"), reset(self)))
    monkeypatch.setattr(SAC, "update",
                        lambda self, b: (calls.append("update"), update(self, b))[1])
    finish = TrainingRun._finish_round

    def mark(self, answers):
        calls.append(f"round {self.feedback.rounds}")
        finish(self, answers)

    monkeypatch.setattr(TrainingRun, "_finish_round", mark)
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "pebble", "steps": 900, "threads": 1, "run_dir": str(tmp_path),
        "reset_updates": 7, "feedback.compare_rule": "uniform"})
    TrainingRun(cfg, progress=False).train()
    first = calls.index("round 0")
    assert calls[first + 1: first + 9] == ["reset"] + ["update"] * 7
    assert calls.count("reset") == 1
    rounds = _rows(tmp_path / "rounds.csv")
    # The diagnostic's column: uniform picks on the disagreement rounds (none on round 0).
    assert rounds[0]["compare_distinguishable_ratio"] == "nan"
    assert 0 <= float(rounds[1]["compare_distinguishable_ratio"]) <= 1
    assert all(-1 <= float(r["reward_corr"]) <= 1 for r in rounds)


def test_the_hooks_hear_of_every_reward_epoch_of_a_round(tmp_path):
    """A round's reward training can run for many minutes: a worker heartbeats after each epoch
    (otherwise its run looks dead and another worker takes it over mid-round)."""

    class CountingHooks(RunHooks):
        def __init__(self) -> None:
            self.steps: list[int] = []

        def reward_epoch(self, step: int) -> None:
            self.steps.append(step)

    hooks = CountingHooks()
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "surf", "steps": 1200, "threads": 1, "run_dir": str(tmp_path / "run")})
    TrainingRun(cfg, progress=False, hooks=hooks).train()
    rounds = _rows(str(tmp_path / "run" / "rounds.csv"))
    assert rounds and len(hooks.steps) == sum(int(r["reward_epochs"]) for r in rounds)
    assert sorted(set(hooks.steps)) == [int(r["step"]) for r in rounds]  # at each round's step


def test_a_run_killed_after_a_round_resumes_past_its_reward_training(tmp_path):
    """A round's reward training is minutes of CPU: the checkpoint written as the round closes
    keeps it, so a run killed soon after goes on without training that round again, and ends
    as an uninterrupted run does."""

    class Killed(Exception):
        pass

    class Hooks(RunHooks):
        def __init__(self, kill: bool) -> None:
            self.kill, self.rounds, self.epochs = kill, 0, []

        def metrics(self, stream, row):
            self.rounds += stream == "rounds"

        def reward_epoch(self, step):
            self.epochs.append(step)

        def stop_requested(self, step):
            if self.kill and self.rounds:
                raise Killed  # the first step after the first round: no periodic checkpoint
            return False

    overrides = {"algo": "pebble", "steps": 1000, "threads": 1, "checkpoint_every": 100_000}
    reference = build_config("dmc:cheetah_run", "tiny",
                             overrides | {"run_dir": str(tmp_path / "reference")})
    TrainingRun(reference, progress=False).train()
    cfg = build_config("dmc:cheetah_run", "tiny", overrides | {"run_dir": str(tmp_path / "cut")})
    first = Hooks(kill=True)
    with pytest.raises(Killed):
        TrainingRun(cfg, progress=False, hooks=first).train()
    trained = sorted(set(first.epochs))
    assert len(trained) == 1  # the first round trained, then the kill

    again = Hooks(kill=False)
    TrainingRun(cfg, resume=True, progress=False, hooks=again).train()
    assert trained[0] not in again.epochs  # that round's training was not done twice
    rounds = _rows(os.path.join(cfg.run_dir, "rounds.csv"))
    assert [r["step"] for r in rounds] == [
        r["step"] for r in _rows(os.path.join(reference.run_dir, "rounds.csv"))]

    def strip(rows):
        return [{k: v for k, v in r.items() if k != "answered_at"} for r in rows]

    assert strip(_labels(cfg.run_dir)) == strip(_labels(reference.run_dir))


def test_an_update_comes_between_the_action_and_the_environments_step(tmp_path, monkeypatch):
    """As in the authors' loops: the update trains on the transitions before the current one,
    so on a GPU it runs while the host steps the simulator."""
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sac", "steps": 400, "threads": 1, "run_dir": str(tmp_path), "update_every": 4})
    run = TrainingRun(cfg, progress=False)
    seen: list[tuple[int, int]] = []
    update = run._update

    def recording_update():
        seen.append((run.step, len(run.buffer)))
        return update()

    monkeypatch.setattr(run, "_update", recording_update)
    run.train()
    # Updates at the steps being made 204, 208, ..., 400: past the 200 seed steps, every 4th.
    assert [step + 1 for step, _ in seen] == list(range(204, 401, 4))
    assert all(stored == step for step, stored in seen)  # not yet the current transition

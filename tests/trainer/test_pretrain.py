"""Skill pretraining and its snapshots: `sepoa pretrain` as a user runs it, and what an online
S-EPOA run gets back from a snapshot."""

import csv
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from runvocab.config import apply_overrides, build_config
from runvocab.snapshot_names import default_snapshot_path, snapshot_path
from trainer.skills import pretrain as pretrain_module
from trainer.skills.pretrain import (
    SkillPretraining,
    build_skill_agent,
    load_snapshot,
    pretrain_once,
)

CPU = torch.device("cpu")
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _tiny(backend: str = "aps", **overrides):
    return build_config("dmc:cheetah_run", "tiny",
                        {"skill.backend": backend, "threads": 1, **overrides})


def test_cli_pretrain_writes_a_plain_snapshot_with_its_metrics(tmp_path):
    env = os.environ | {"PYTHONPATH": REPO, "MUJOCO_GL": "egl"}
    out = subprocess.run(
        [sys.executable, "-m", "sepoa.cli", "pretrain", "--task", "dmc:cheetah_run", "--skills",
         "aps", "--preset", "tiny", "--seed", "0", "--threads", "1", "--no-progress"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    # the default place and name: task, backend, steps and seed, relative to where it ran
    assert re.fullmatch(r"snapshots/dmc-cheetah_run-aps-300-s0-[0-9a-f]{10}\.pt",
                        summary["snapshot"])
    # ... the very snapshot an online run of these settings starts from
    online = build_config("dmc:cheetah_run", "tiny", {"skill.backend": "aps", "seed": 0})
    assert summary["snapshot"] == snapshot_path(online)
    path = tmp_path / summary["snapshot"]
    state = torch.load(path, weights_only=True)  # plain data: no pickled objects
    assert state["task"] == "dmc:cheetah_run" and state["backend"] == "aps"
    assert state["skill_dim"] == 10 and state["steps"] == 300
    assert state["config"]["skill"]["update_skill_every"] == 5  # resolved, not 0
    assert str(tmp_path) not in repr(state)  # nothing in it depends on where it was written
    with open(path.with_suffix(".csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["step"]) for r in rows] == [200]  # one finished 200-step episode
    assert float(rows[0]["fps"]) > 0 and rows[0]["intrinsic_reward"] != ""
    assert rows[0]["aps_loss"] != "" and rows[0]["critic_loss"] != ""

    # a second run with the same arguments does not overwrite the first one's snapshot
    again = subprocess.run(out.args, capture_output=True, text=True, timeout=300, cwd=tmp_path,
                           env=env)
    assert again.returncode == 2 and "exists already" in again.stderr


def test_cli_pretrain_told_to_go_saves_its_progress_and_the_same_command_goes_on(tmp_path):
    env = os.environ | {"PYTHONPATH": REPO, "MUJOCO_GL": "egl"}
    command = [sys.executable, "-m", "sepoa.cli", "pretrain", "--task", "dmc:cheetah_run",
               "--preset", "tiny", "--steps", "100000", "--checkpoint_every", "1000000",
               "--threads", "1", "--no-progress", "--quality-skills", "0", "--out", "s.pt"]
    first = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while _last_step(tmp_path / "s.csv") == 0:  # an episode ended
        assert first.poll() is None and time.monotonic() < deadline
        time.sleep(0.1)
    first.send_signal(signal.SIGTERM)
    _, err = first.communicate(timeout=120)
    assert first.returncode == 128 + signal.SIGTERM, err
    lines = err.strip().splitlines()
    assert re.fullmatch(r"sepoa pretrain: SIGTERM at step \d+: leaving at the end of this "
                        r"episode with the progress saved \(again to stop at once\)", lines[-2])
    left = re.fullmatch(r"sepoa pretrain: pretraining left at step (\d+) of 100000, its "
                        r"progress saved in s\.pt\.partial; the same command goes on from "
                        r"there", lines[-1])
    assert left is not None, err
    step = int(left.group(1))
    assert step % 200 == 0 and (tmp_path / "s.pt.partial").exists()
    # The same command goes on from that step.
    again = subprocess.Popen(command, cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    while _last_step(tmp_path / "s.csv") <= step:
        assert again.poll() is None and time.monotonic() < deadline
        time.sleep(0.1)
    again.send_signal(signal.SIGTERM)
    _, err = again.communicate(timeout=120)
    assert again.returncode == 128 + signal.SIGTERM, err
    assert f"pretraining goes on from step {step} of 100000" in err


def _last_step(csv_path) -> int:
    """The step of the last episode a pretraining's metrics file holds (0: none yet)."""
    lines = csv_path.read_text().splitlines() if csv_path.exists() else []
    return int(lines[-1].split(",", 1)[0]) if len(lines) > 1 else 0


@pytest.mark.parametrize("backend", ["aps", "diayn", "cic"])
def test_a_snapshot_restores_the_pretrained_agent_exactly(tmp_path, backend):
    run = SkillPretraining(_tiny(backend), out=str(tmp_path / "s.pt"), progress=False)
    path = run.run()
    snap = load_snapshot(path, "dmc:cheetah_run", backend)

    # an online run: another seed, the fine-tuning learning rate, the same widths
    online = _tiny(backend, seed=7, **{"sac.lr": 5e-4})
    agent, skills = build_skill_agent(online, run.obs_dim, run.action_dim, CPU, snap)
    fresh, _ = build_skill_agent(online, run.obs_dim, run.action_dim, CPU, None)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(5, run.obs_dim)).astype(np.float32)
    z = skills.sample_skills(rng, 5)
    for o, zi in zip(obs, z, strict=True):
        restored = agent.act(o, zi, rng, deterministic=True)
        np.testing.assert_array_equal(restored, run.agent.act(o, zi, rng, deterministic=True))
        assert not np.allclose(restored, fresh.act(o, zi, rng, deterministic=True))
    # the critic (and target) come along: the online phase starts from the pretrained Q
    o, a = torch.from_numpy(obs), torch.zeros(5, run.action_dim)
    torch.testing.assert_close(agent.q(o, a, torch.from_numpy(z)),
                               run.agent.q(o, a, torch.from_numpy(z)))
    assert agent.sac.cfg.lr == 5e-4  # fine-tuning's optimiser, not pretraining's
    batch = run.buffer.sample(16)
    torch.testing.assert_close(skills.intrinsic_reward(batch),
                               run.backend.intrinsic_reward(batch))


def test_skills_change_every_few_steps_and_at_each_episode_start(tmp_path):
    run = SkillPretraining(_tiny("aps", **{"skill.pretrain_steps": 260}),
                           out=str(tmp_path / "s.pt"), progress=False)
    run.run()
    skills = run.buffer.skill[: run.buffer.size].numpy()
    changes = [t for t in range(1, len(skills)) if not np.array_equal(skills[t], skills[t - 1])]
    # every 5 steps, and at step 200, where the second 200-step episode starts
    assert changes == sorted(set(range(5, 260, 5)) | {200})
    np.testing.assert_allclose(np.linalg.norm(skills, axis=1), 1.0, rtol=1e-5)


def test_no_pretraining_is_fresh_nets_and_zero_steps_is_a_valid_snapshot(tmp_path):
    cfg = _tiny("aps", **{"skill.pretrain_steps": 0})
    path = SkillPretraining(cfg, out=str(tmp_path / "s.pt"), progress=False).run()
    snap = load_snapshot(path, "dmc:cheetah_run")
    assert snap.steps == 0
    torch.manual_seed(123)
    agent, backend = build_skill_agent(cfg, 17, 6, CPU)  # the paper's "no pretraining" ablation
    assert backend.name == "aps" and agent.successor_features and agent.skill_dim == 10


def test_load_snapshot_refuses_a_snapshot_of_another_run_with_a_clear_message(tmp_path):
    path = SkillPretraining(_tiny("diayn", **{"skill.pretrain_steps": 0}),
                            out=str(tmp_path / "s.pt"), progress=False).run()
    with pytest.raises(ValueError, match="pretrained on 'dmc:cheetah_run', not on this run's "
                       "task 'dmc:walker_run'"):
        load_snapshot(path, "dmc:walker_run")
    with pytest.raises(ValueError, match="holds 'diayn' skills.*skill.backend 'aps'"):
        load_snapshot(path, "dmc:cheetah_run", "aps")
    with pytest.raises(ValueError, match="skills of size 16.*skill_dim 8"):
        load_snapshot(path, "dmc:cheetah_run", "diayn", 8)
    with pytest.raises(FileNotFoundError, match="sepoa pretrain --task dmc:cheetah_run"):
        load_snapshot(str(tmp_path / "missing.pt"), "dmc:cheetah_run")
    (tmp_path / "junk.pt").write_bytes(b"not a snapshot")
    with pytest.raises(ValueError, match="not a readable skill snapshot"):
        load_snapshot(str(tmp_path / "junk.pt"), "dmc:cheetah_run")
    # nets of another width cannot take the weights: said in the run's own terms
    snap = load_snapshot(path, "dmc:cheetah_run")
    wide = _tiny("diayn", **{"sac.hidden_dim": 64})
    with pytest.raises(ValueError, match="32 wide x 2 layers.*sac.hidden_dim=64"):
        build_skill_agent(wide, 17, 6, CPU, snap)


def test_default_snapshot_name_and_pretraining_presets():
    cfg = build_config("dmc:quadruped_run", "paper", {"skill.backend": "cic", "seed": 2})
    name = r"dmc-quadruped_run-cic-1000000-s{}-[0-9a-f]{{10}}\.pt"  # the paper: 1 M for quadruped
    assert re.fullmatch(os.path.join("snapshots", name.format(2)), default_snapshot_path(cfg))
    # By default an online run starts from the snapshot of its own seed: the name
    # `sepoa pretrain --seed 2` gives the same settings.
    assert snapshot_path(cfg) == default_snapshot_path(cfg)
    assert snapshot_path(dataclasses.replace(cfg, seed=3)) != snapshot_path(cfg)
    # A fixed skill.snapshot_seed shares one snapshot among runs of every seed.
    fixed = apply_overrides(cfg, {"skill.snapshot_seed": 0})
    assert re.fullmatch(os.path.join("snapshots", name.format(0)), snapshot_path(fixed))
    assert snapshot_path(dataclasses.replace(fixed, seed=5)) == snapshot_path(fixed)
    # Settings only the online phase reads share it; one pretraining reads does not.
    online = apply_overrides(cfg, {"skill.estimator_steps": 5, "skill.reset_critic": False})
    assert snapshot_path(online) == snapshot_path(cfg)
    assert snapshot_path(apply_overrides(cfg, {"skill.beta": 1.0})) != snapshot_path(cfg)
    shared = dataclasses.replace(cfg, skill=dataclasses.replace(cfg.skill, snapshot="x/s0.pt"))
    assert snapshot_path(shared) == "x/s0.pt"  # any run can name the snapshot it starts from
    paper = build_config("dmc:cheetah_run", "paper")
    assert (paper.skill.pretrain_steps, paper.skill.lr, paper.skill.beta,
            paper.skill.knn_k) == (500_000, 1e-4, 5.0, 12)
    assert (paper.sac.hidden_dim, paper.sac.batch_size, paper.skill.hidden_dim) == (1024,) * 3
    small = build_config("dmc:cheetah_run", "small")
    assert (small.sac.hidden_dim, small.sac.batch_size, small.skill.hidden_dim) == (256,) * 3


def test_a_run_that_must_pretrain_first_reports_each_pretraining_step(tmp_path):
    from trainer.hooks import RunHooks
    from trainer.loop import TrainingRun

    class Recorder(RunHooks):
        def __init__(self):
            self.steps = []

        def pretraining(self, step):
            self.steps.append(step)

    hooks = Recorder()
    cfg = build_config("dmc:cheetah_run", "tiny", {
        "algo": "sepoa", "steps": 10, "run_dir": str(tmp_path / "run"),
        "skill.snapshot": str(tmp_path / "skills.pt"), "threads": 1})
    TrainingRun(cfg, progress=False, hooks=hooks)
    # A worker heartbeats from these, so a long pretraining keeps its run.
    assert hooks.steps == list(range(1, cfg.skill.pretrain_steps + 1))
    assert os.path.exists(tmp_path / "skills.pt")


def test_runs_needing_one_snapshot_pretrain_it_once(tmp_path, monkeypatch) -> None:
    """Workers starting S-EPOA runs of one task at once: one pretrains, the others wait for its
    snapshot (heartbeating meanwhile) and load it."""
    import threading
    import time

    from trainer.skills import pretrain as module

    made: list[str] = []

    def slow_pretrain(cfg, out, progress, tick):
        made.append(out)
        time.sleep(0.5)
        with open(out, "w") as f:
            f.write("snapshot")
        return out

    monkeypatch.setattr(module, "pretrain", slow_pretrain)
    cfg = build_config("dmc:cheetah_run", "tiny", {"algo": "sepoa",
                                                   "skill.snapshot_dir": str(tmp_path)})
    path = snapshot_path(cfg)
    waits: list[int] = []
    results: list[bool] = []
    start = threading.Barrier(3)

    def worker() -> None:
        start.wait()
        results.append(module.pretrain_once(cfg, path, waiting=lambda: waits.append(1),
                                            poll_seconds=0.05))

    threads = [threading.Thread(target=worker) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10)
    assert made == [path] and sorted(results) == [False, False, True]
    assert waits  # the others waited, calling back (a worker's heartbeat)
    assert module.pretrain_once(cfg, path) is False and made == [path]


class Stopped(Exception):
    """What the tests below raise to stop a pretraining midway, as a kill would."""


def _stop_at(step: int):
    def tick(now: int) -> None:
        if now == step:
            raise Stopped
    return tick


def _snapshot_tensors(path) -> dict[str, torch.Tensor]:
    def flat(prefix, obj):
        if isinstance(obj, torch.Tensor):
            yield prefix, obj
        elif isinstance(obj, dict):
            for k, v in obj.items():
                yield from flat(f"{prefix}.{k}", v)
    state = torch.load(path, weights_only=True)
    return dict(flat("", {"agent": state["agent"], "skill_nets": state["skill_nets"]}))


def _rows(path) -> list[dict[str, str]]:
    with open(os.path.splitext(path)[0] + ".csv", newline="") as f:
        return [{k: v for k, v in r.items() if k != "fps"} for r in csv.DictReader(f)]


def test_a_pretraining_stopped_midway_goes_on_to_the_snapshot_an_unstopped_one_writes(
        tmp_path, capsys):
    steps = {"skill.pretrain_steps": 700}
    straight = str(tmp_path / "straight.pt")  # never checkpointed
    SkillPretraining(_tiny("aps", checkpoint_every=10_000, **steps), out=straight,
                     progress=False).run()

    cfg = _tiny("aps", checkpoint_every=200, **steps)
    out = str(tmp_path / "stopped.pt")
    with pytest.raises(Stopped):  # killed at step 500, past its checkpoints at 200 and 400
        SkillPretraining(cfg, out=out, progress=False, tick=_stop_at(500)).run()
    assert os.path.exists(out + ".partial") and not os.path.exists(out)
    assert [int(r["step"]) for r in _rows(out)] == [200, 400]

    resumed = SkillPretraining(cfg, out=out, progress=False)
    assert resumed.resumed_from == 400
    resumed.run()
    assert "pretraining goes on from step 400 of 700" in capsys.readouterr().err
    assert not os.path.exists(out + ".partial")  # gone with the snapshot written

    ours, theirs = _snapshot_tensors(out), _snapshot_tensors(straight)
    assert ours.keys() == theirs.keys() and len(ours) > 10
    for name, tensor in ours.items():
        assert torch.equal(tensor, theirs[name]), name  # bit for bit
    # Every episode's metrics once, as the straight run logged them (steps/s aside).
    assert _rows(out) == _rows(straight) and len(_rows(out)) == 3


def test_a_pretraining_checkpoint_of_other_settings_or_unreadable_is_refused_by_name(tmp_path):
    out = str(tmp_path / "s.pt")
    with pytest.raises(Stopped):
        SkillPretraining(_tiny("aps", checkpoint_every=200), out=out, progress=False,
                         tick=_stop_at(250)).run()
    with pytest.raises(ValueError, match=r"s\.pt\.partial holds a pretraining with other "
                       r"settings \(seed 0 there, 3 here\); remove it"):
        SkillPretraining(_tiny("aps", seed=3, checkpoint_every=200), out=out, progress=False)
    # A setting that leaves the snapshot as it is (the checkpoint period) may change.
    assert SkillPretraining(_tiny("aps", checkpoint_every=50), out=out,
                            progress=False).resumed_from == 200
    with open(out + ".partial", "wb") as f:
        f.write(b"cut short")
    with pytest.raises(ValueError, match="not a readable pretraining checkpoint.*remove it"):
        SkillPretraining(_tiny("aps"), out=out, progress=False)


def test_a_run_told_to_go_while_pretraining_saves_its_progress_at_the_episodes_end(
        tmp_path):
    """A worker told to go while an S-EPOA run pretrains its snapshot leaves at the end of the
    episode with the pretraining's progress saved; the next worker's run pretrains on from
    there, not from its last periodic checkpoint or step 0, to the snapshot an uninterrupted
    pretraining writes."""
    from trainer.hooks import RunHooks
    from trainer.loop import TrainingRun
    from trainer.skills.pretrain import PretrainingLeft

    class Departing(RunHooks):
        def __init__(self, leave_at: int | None):
            self.steps: list[int] = []
            self.leave_at = leave_at

        def pretraining(self, step):
            self.steps.append(step)
            return self.leave_at is not None and step >= self.leave_at

    settings = {"algo": "sepoa", "steps": 10, "threads": 1, "skill.pretrain_steps": 700,
                "checkpoint_every": 100_000}  # no periodic checkpoint within the pretraining
    cfg = build_config("dmc:cheetah_run", "tiny", settings | {
        "run_dir": str(tmp_path / "run"), "skill.snapshot": str(tmp_path / "skills.pt")})
    first = Departing(leave_at=250)
    with pytest.raises(PretrainingLeft, match="left at step 400 of 700"):
        TrainingRun(cfg, progress=False, hooks=first)
    assert first.steps[-1] == 400  # the end of the episode it was told in (200 steps each)
    assert os.path.exists(tmp_path / "skills.pt.partial")
    second = Departing(leave_at=None)
    TrainingRun(cfg, progress=False, hooks=second)
    assert second.steps == list(range(401, 701))  # on from 400
    assert not os.path.exists(tmp_path / "skills.pt.partial")
    straight = build_config("dmc:cheetah_run", "tiny", settings | {
        "run_dir": str(tmp_path / "straight"), "skill.snapshot": str(tmp_path / "straight.pt")})
    TrainingRun(straight, progress=False)
    ours, theirs = _snapshot_tensors(tmp_path / "skills.pt"), _snapshot_tensors(
        tmp_path / "straight.pt")
    assert ours.keys() == theirs.keys() and len(ours) > 10
    for name, tensor in ours.items():
        assert torch.equal(tensor, theirs[name]), name  # bit for bit


def test_a_snapshot_a_longer_pretraining_wrote_on_its_way_is_taken_for_a_shorter_one(
        tmp_path, monkeypatch, capsys):
    folder = str(tmp_path / "snapshots")
    longer = _tiny("aps", **{"skill.pretrain_steps": 600, "skill.snapshot_dir": folder})
    SkillPretraining(longer, progress=False, quality_skills=0, snapshots_at=(400,)).run()
    straight = str(tmp_path / "straight.pt")  # what a 400-step pretraining writes
    shorter = _tiny("aps", **{"skill.pretrain_steps": 400, "skill.snapshot_dir": folder})
    SkillPretraining(shorter, out=straight, progress=False, quality_skills=0).run()

    path = default_snapshot_path(shorter)
    assert not os.path.exists(path)
    assert pretrain_once(shorter, path) is False  # taken, not pretrained
    assert "wrote at 400 steps" in capsys.readouterr().err
    ours, theirs = _snapshot_tensors(path), _snapshot_tensors(straight)
    assert ours.keys() == theirs.keys() and len(ours) > 10
    for name, tensor in ours.items():
        assert torch.equal(tensor, theirs[name]), name  # bit for bit

    # Another setting pretraining reads, or another seed: pretrained afresh.
    pretrained = []
    monkeypatch.setattr(pretrain_module, "pretrain",
                        lambda cfg, out, **_: pretrained.append(out) or out)
    for other in (_tiny("aps", **{"skill.pretrain_steps": 400, "skill.snapshot_dir": folder,
                                  "skill.lr": 3e-4}),
                  dataclasses.replace(shorter, seed=1)):
        other_path = default_snapshot_path(other)
        assert pretrain_once(other, other_path) is True and pretrained[-1] == other_path

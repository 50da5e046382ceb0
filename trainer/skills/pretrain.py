"""Skill pretraining (S-EPOA's `Unsupervised Pretrain`) and the snapshot it leaves.

`pretrain(cfg)` runs `skill.seed_steps` of random actions, then SAC updates of pi(a|s,z) on the
backend's intrinsic reward, with a fresh skill every `skill.update_skill_every` steps and at
every episode start (URLB's schedule). It writes one snapshot and, beside it, a CSV of
per-episode metrics (the task's own return, for information only; the mean intrinsic reward,
losses and steps/s), and the snapshot's skill quality: the task return of 50 random skills
against uniform random actions (`trainer.skills.quality`, `<snapshot>.quality.json`);
`snapshots_at` adds snapshots on the way (`intermediate_path`), each with its quality. The
snapshot is a plain state dict (tensors, numbers, strings; loadable
with `torch.load(weights_only=True)`, written atomically) holding the task, backend, sizes,
the configuration used, the agent's weights and the backend's nets, and no path: any number of
online runs of the task load it with `load_snapshot` and `build_skill_agent`.
`build_skill_agent(..., snapshot=None)` gives fresh nets: the paper's "no pretraining" ablation.

Pretraining is hours of a run's life, so it is resumable: every `checkpoint_every` steps, at an
episode's end, it writes its whole state (nets, optimisers, replay buffer, every RNG) to
`<snapshot>.partial`, and a pretraining of the same settings started later (a worker taking the
run over, `sepoa pretrain` again) goes on from there, to the very snapshot an uninterrupted one
writes. The file goes once the snapshot is written.
"""

from __future__ import annotations

import dataclasses
import fcntl
import glob
import json
import os
import shutil
import sys
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import torch
from tqdm import tqdm  # type: ignore[import-untyped]

from runvocab.config import RunConfig, from_dict, to_dict
from runvocab.snapshot_names import (
    default_snapshot_path,
    intermediate_path,
    longer_pattern,
    progress_path,
    snapshot_settings,
)
from runvocab.validate import validate
from trainer.checkpoint import (
    load_checkpoint,
    random_state,
    restore_random_state,
    save_checkpoint,
)
from trainer.envs import make_env
from trainer.metrics import CSVStream
from trainer.sac import UpdateMetrics
from trainer.schedule import Period
from trainer.skills import (
    SkillAgent,
    SkillBackend,
    SkillReplayBuffer,
    make_skill_backend,
    quality,
    resolve_skill_config,
)
from trainer.skills.common import mean_metrics
from trainer.utils import pick_device, set_seed

SNAPSHOT_FORMAT = "sepoa-skill-snapshot/1"
PROGRESS_FORMAT = "sepoa-skill-pretraining-progress/1"


class Snapshot(NamedTuple):
    task: str
    backend: str
    skill_dim: int
    obs_dim: int
    action_dim: int
    steps: int
    """pretraining steps taken (0: fresh nets)"""
    seed: int
    config: dict[str, Any]
    """the pretraining run's RunConfig as a dict, skill fields resolved"""
    agent: dict
    """`SkillAgent.weights()`"""
    skill_nets: dict
    """`SkillBackend.state_dict()`"""


def check_pretrain_config(cfg: RunConfig) -> RunConfig:
    """`cfg` with its skill fields resolved; a ConfigError naming the field for a bad one."""
    validate(cfg, pretraining=True)
    return dataclasses.replace(cfg, skill=resolve_skill_config(cfg.skill))


def build_skill_agent(cfg: RunConfig, obs_dim: int, action_dim: int, device: torch.device,
                      snapshot: Snapshot | None = None) -> tuple[SkillAgent, SkillBackend]:
    """The agent pi(a|s,z) with its critic, and the skill backend, for `cfg.skill` and `cfg.sac`
    (its lr, batch, ...): with a snapshot's weights, or fresh nets when `snapshot` is None."""
    skill = resolve_skill_config(cfg.skill)
    if snapshot is not None:
        if (snapshot.obs_dim, snapshot.action_dim) != (obs_dim, action_dim):
            raise ValueError(f"the snapshot's observation/action sizes ({snapshot.obs_dim}, "
                             f"{snapshot.action_dim}) are not this env's ({obs_dim}, "
                             f"{action_dim})")
        # The skill nets as pretrained; sizes and the reward's constants come from the snapshot.
        skill = resolve_skill_config(dataclasses.replace(
            skill, **{k: v for k, v in snapshot.config["skill"].items()
                      if k not in ("snapshot", "snapshot_dir")}))
    backend = make_skill_backend(skill.backend, obs_dim, skill, device)
    agent = SkillAgent(obs_dim, action_dim, backend.skill_dim, cfg.sac, device,
                       backend.successor_features)
    if snapshot is not None:
        try:
            agent.load_weights(snapshot.agent)
        except RuntimeError as err:
            pre = snapshot.config["sac"]
            raise ValueError(
                f"the snapshot's nets ({pre['hidden_dim']} wide x {pre['hidden_layers']} layers) "
                f"do not fit this run's sac.hidden_dim={cfg.sac.hidden_dim}, "
                f"sac.hidden_layers={cfg.sac.hidden_layers}") from err
        backend.load_state_dict(snapshot.skill_nets)
    return agent, backend


def save_snapshot(path: str, cfg: RunConfig, agent: SkillAgent, backend: SkillBackend,
                  obs_dim: int, action_dim: int, steps: int) -> None:
    """Write the snapshot atomically (parent folders made as needed)."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    save_checkpoint(path, {
        "format": SNAPSHOT_FORMAT,
        "task": cfg.task,
        "backend": backend.name,
        "skill_dim": backend.skill_dim,
        "obs_dim": obs_dim,
        "action_dim": action_dim,
        "steps": steps,
        "seed": cfg.seed,
        "config": to_dict(cfg),
        "agent": agent.weights(),
        "skill_nets": backend.state_dict(),
    })


def load_snapshot(path: str, expected_task: str, expected_backend: str | None = None,
                  expected_skill_dim: int | None = None) -> Snapshot:
    """The snapshot at `path`, checked against what the run expects; FileNotFoundError or
    ValueError with the reason otherwise."""
    if not os.path.exists(path):
        raise FileNotFoundError(
            f"no skill snapshot at {path}; make one with `sepoa pretrain --task {expected_task} "
            f"--skills {expected_backend or 'aps'} ...` (or pass its path)")
    try:
        state = load_checkpoint(path)
    except Exception as err:  # torch raises several types for a file that is no checkpoint
        raise ValueError(f"{path} is not a readable skill snapshot: {err}") from err
    if not isinstance(state, dict) or state.get("format") != SNAPSHOT_FORMAT:
        raise ValueError(f"{path} is not a skill snapshot (format "
                         f"{state.get('format') if isinstance(state, dict) else None!r}, "
                         f"expected {SNAPSHOT_FORMAT!r})")
    snap = Snapshot(**{f: state[f] for f in Snapshot._fields})
    if snap.task != expected_task:
        raise ValueError(f"snapshot {path} was pretrained on {snap.task!r}, not on this run's "
                         f"task {expected_task!r}")
    if expected_backend is not None and snap.backend != expected_backend:
        raise ValueError(f"snapshot {path} holds {snap.backend!r} skills, but this run uses "
                         f"skill.backend {expected_backend!r}")
    if expected_skill_dim and snap.skill_dim != expected_skill_dim:
        raise ValueError(f"snapshot {path} has skills of size {snap.skill_dim}, but this run "
                         f"asks for skill.skill_dim {expected_skill_dim}")
    return snap


class PretrainingLeft(Exception):
    """Told to leave (`tick` returned True): the pretraining stopped at an episode's end with
    its progress saved, and the next pretraining of its settings goes on from there."""


class SkillPretraining:
    """One pretraining run: the env, the agent, the backend and the replay buffer; `run()`
    trains and writes the snapshot."""

    def __init__(self, cfg: RunConfig, out: str | None = None, progress: bool = True,
                 tick: Callable[[int], bool | None] | None = None, quality_skills: int = 50,
                 snapshots_at: tuple[int, ...] = ()):
        cfg = check_pretrain_config(cfg)
        self.cfg, self.progress = cfg, progress
        self.tick = tick
        """called with the step after every step (a worker heartbeats from it); True: leave at
        the end of this episode, the progress saved (`PretrainingLeft`)"""
        self.quality_skills = quality_skills
        """random skills whose task return is measured beside each snapshot (0: none)"""
        if quality_skills and quality_skills < quality.TOP:
            raise ValueError(f"--quality-skills takes 0 (no measurement) or at least "
                             f"{quality.TOP}, got {quality_skills}")
        bad = [s for s in snapshots_at if not 0 < s < cfg.skill.pretrain_steps]
        if bad:
            raise ValueError(f"intermediate snapshots must lie between 0 and the pretraining "
                             f"length {cfg.skill.pretrain_steps}, got {bad}")
        self.snapshots_at = tuple(sorted(set(snapshots_at)))
        """steps at which a snapshot is also written, `intermediate_path` (at episode ends:
        the first episode end at or after each)"""
        self.path = out or default_snapshot_path(cfg)
        if os.path.exists(self.path):
            raise FileExistsError(f"{self.path} exists already; remove it or choose another "
                                  "--out")
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        set_seed(cfg.seed)
        self.device = pick_device(cfg.device)
        self.env = make_env(cfg.task, cfg.seed, cfg.episode_length or None)
        self.obs_dim, self.action_dim = self.env.obs_dim, self.env.action_dim
        # Pretraining's learning rate; the widths and batch are the run's, so the online phase
        # loads the weights into nets of the same shape.
        pre_cfg = dataclasses.replace(cfg, sac=dataclasses.replace(cfg.sac, lr=cfg.skill.lr))
        self.agent, self.backend = build_skill_agent(pre_cfg, self.obs_dim, self.action_dim,
                                                     self.device)
        capacity = max(1, min(cfg.replay_capacity, cfg.skill.pretrain_steps))
        self.buffer = SkillReplayBuffer(self.obs_dim, self.action_dim, self.backend.skill_dim,
                                        capacity, self.device, cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.step = self.episode = 0
        self.progress_file = progress_path(self.path)
        self.checkpoints = Period(max(cfg.checkpoint_every, 1))  # 0: at every episode's end
        self.resumed_from = 0
        """the step this pretraining went on from (0: it started afresh)"""
        self.settings = json.dumps(snapshot_settings(cfg, cfg.seed), sort_keys=True,
                                   default=str)
        """what its checkpoint must match to be gone on from"""
        if os.path.exists(self.progress_file):
            self._load_progress()

    def _save_progress(self) -> None:
        """Everything `run` needs to go on from this episode's end as if never stopped."""
        self.checkpoints.happened(self.step)
        state = {
            "format": PROGRESS_FORMAT, "settings": self.settings,
            "step": self.step, "episode": self.episode,
            "agent": self.agent.state_dict(), "skill_nets": self.backend.state_dict(),
            "buffer": self.buffer.state_dict(), "env_rng": self.env.rng_state(),
        } | random_state(self.rng, self.device)
        save_checkpoint(self.progress_file, state)

    def _load_progress(self) -> None:
        where = self.progress_file
        try:
            state = load_checkpoint(where)
        except Exception:  # noqa: BLE001 - torch raises several kinds for a bad file
            raise ValueError(f"{where} is not a readable pretraining checkpoint (cut short or "
                             "another file); remove it to pretrain from the start") from None
        if not isinstance(state, dict) or state.get("format") != PROGRESS_FORMAT:
            raise ValueError(f"{where} is not a pretraining checkpoint; remove it to pretrain "
                             "from the start")
        if state["settings"] != self.settings:
            differ = sorted(_differences(json.loads(state["settings"]), json.loads(self.settings)))
            raise ValueError(f"{where} holds a pretraining with other settings ("
                             f"{', '.join(differ)}); remove it to pretrain from the start, or "
                             "pretrain with its settings")
        self.agent.load_state_dict(state["agent"])
        self.backend.load_state_dict(state["skill_nets"])
        self.buffer.load_state_dict(state["buffer"])
        restore_random_state(state, self.rng, self.device)
        self.env.set_rng_state(state["env_rng"])
        self.step = self.resumed_from = state["step"]
        self.episode = state["episode"]
        self.checkpoints.happened(self.step)

    def _update(self) -> UpdateMetrics:
        batch = self.buffer.sample(self.cfg.sac.batch_size)
        metrics = self.backend.update(batch)
        # URLB's order: the skill nets step first, then reward the batch with the new nets.
        reward = self.backend.intrinsic_reward(batch)
        metrics |= self.agent.update(batch._replace(reward=reward))
        return metrics | {"intrinsic_reward": reward.detach().mean()}

    def run(self) -> str:
        """Pretrain for `skill.pretrain_steps` steps, save the snapshot, return its path."""
        s, env, rng = self.cfg.skill, self.env, self.rng
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        metrics_path = os.path.splitext(self.path)[0] + ".csv"
        if self.resumed_from:
            print(f"pretraining goes on from step {self.resumed_from} of {s.pretrain_steps} "
                  f"({self.progress_file}; remove it to start afresh)", file=sys.stderr,
                  flush=True)
            CSVStream(metrics_path).keep_rows(lambda r: int(r["step"]) <= self.resumed_from)
        elif os.path.exists(metrics_path):  # left by a run killed before its first checkpoint
            os.remove(metrics_path)
        stream = CSVStream(metrics_path)
        episode_return = 0.0
        updates: list[UpdateMetrics] = []
        start = time.time()
        bar = tqdm(total=s.pretrain_steps, initial=self.step, disable=not self.progress,
                   dynamic_ncols=True, unit="step")
        obs, new_episode, leaving = env.reset(), True, False
        while self.step < s.pretrain_steps:
            if new_episode or self.step % s.update_skill_every == 0:
                skill = self.backend.sample_skills(rng, 1)[0]
            new_episode = False
            if self.step < s.seed_steps:
                action = rng.uniform(-1, 1, self.action_dim).astype(np.float32)
            else:
                action = self.agent.act(obs, skill, rng).astype(np.float32)
            result = env.step(action)
            # The stored reward is unused: the intrinsic reward is computed per batch.
            self.buffer.add(obs, action, 0.0, result.reward, result.obs, skill)
            obs, episode_return = result.obs, episode_return + result.reward
            self.step += 1
            if self.step > s.seed_steps and self.step % s.update_every == 0:
                updates.append(self._update())
            bar.update(1)
            if self.tick is not None and self.tick(self.step):
                leaving = True
            if result.done:
                self.episode += 1
                row = {"step": self.step, "episode": self.episode, "return": episode_return,
                       "fps": (self.step - self.resumed_from) / max(time.time() - start, 1e-9)}
                row |= mean_metrics(updates)
                stream.write(row)
                if updates:
                    bar.set_postfix(r_int=f"{row['intrinsic_reward']:.3f}", refresh=False)
                updates, episode_return = [], 0.0
                self._intermediate_snapshots()
                if (self.checkpoints.due(self.step) or leaving) and self.step < s.pretrain_steps:
                    self._save_progress()  # before the reset, whose RNG draws it keeps
                if leaving and self.step < s.pretrain_steps:
                    bar.close()
                    env.close()
                    raise PretrainingLeft(f"pretraining left at step {self.step} of "
                                          f"{s.pretrain_steps}, its progress saved in "
                                          f"{self.progress_file}")
                obs, new_episode = env.reset(), True
        bar.close()
        env.close()
        self._snapshot(self.path)
        if os.path.exists(self.progress_file):
            os.remove(self.progress_file)
        return self.path

    def _intermediate_snapshots(self) -> None:
        """The snapshots due by now that are not written yet (a resumed run wrote some)."""
        for at in self.snapshots_at:
            path = intermediate_path(self.path, at)
            if self.step >= at and not os.path.exists(path):
                self._snapshot(path)

    def _snapshot(self, path: str) -> None:
        """Write a snapshot of the agent as it is, and its skill quality beside it."""
        save_snapshot(path, self.cfg, self.agent, self.backend, self.obs_dim, self.action_dim,
                      self.step)
        if not self.quality_skills:
            return
        measured = quality.measure(self.agent, self.backend, self.cfg.task, self.cfg.seed,
                                   self.cfg.episode_length or None, self.quality_skills)
        quality.write(path, measured, self.step)
        print(f"{os.path.basename(path)} at {self.step} steps: {quality.line(measured)}",
              file=sys.stderr, flush=True)


def _differences(saved: dict, ours: dict, prefix: str = "") -> list[str]:
    """The dotted names of the settings two `snapshot_settings` dicts disagree on."""
    out = []
    for key in sorted(set(saved) | set(ours)):
        a, b = saved.get(key), ours.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append(f"{prefix}{key} {a!r} there, {b!r} here")
    return out


def pretrain(cfg: RunConfig, out: str | None = None, progress: bool = True,
             tick: Callable[[int], bool | None] | None = None, quality_skills: int = 50,
             snapshots_at: tuple[int, ...] = ()) -> str:
    """Pretrain skills for `cfg.task` with `cfg.skill`; returns the snapshot's path (`out`, by
    default `default_snapshot_path(cfg)`). Refuses to overwrite an existing snapshot; goes on
    from `<out>.partial` where an unfinished pretraining left one. `tick` is called with the
    step after every step; where it returns True, the pretraining leaves at the end of the
    episode with its progress saved (`PretrainingLeft`). Beside each snapshot (the final one
    and those at `snapshots_at`) goes the task return of `quality_skills` random skills
    against random actions (`trainer.skills.quality`)."""
    return SkillPretraining(cfg, out, progress, tick, quality_skills, snapshots_at).run()


def pretrain_once(cfg: RunConfig, path: str, tick: Callable[[int], bool | None] | None = None,
                  waiting: Callable[[], None] | None = None, poll_seconds: float = 1.0) -> bool:
    """Make the snapshot at `path` unless it exists: under a lock on `<path>.lock`, so that of
    the processes (workers, hosts sharing the folder) needing one snapshot, one pretrains it and
    the others wait for it, calling `waiting` every `poll_seconds` (a worker heartbeats there).
    True when this call pretrained it."""
    if os.path.exists(path):
        return False
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(f"{path}.lock", "a") as lock:
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if waiting is not None:
                    waiting()
                time.sleep(poll_seconds)
        try:
            if os.path.exists(path):  # made by the process that held the lock before
                return False
            if copy_from_longer(cfg, path):
                return False
            pretrain(cfg, out=path, progress=False, tick=tick)
            return True
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def copy_from_longer(cfg: RunConfig, path: str) -> str | None:
    """Make the snapshot at `path` a copy of one a longer pretraining wrote on its way at this
    length (`intermediate_path`), when every other setting pretraining reads is the same; the
    copy's path, or None when there is none. Pretraining does not read its own length before it
    ends (the replay buffer holds the same transitions up to it), so that snapshot is the one
    this pretraining would write (tests/trainer/test_pretrain.py checks it tensor by tensor)."""
    steps = cfg.skill.pretrain_steps
    # As a snapshot stores its configuration: with the skill fields resolved.
    ours = json.dumps(snapshot_settings(check_pretrain_config(cfg), cfg.seed), sort_keys=True,
                      default=str)
    pattern = longer_pattern(cfg, cfg.seed)
    for candidate in sorted(glob.glob(os.path.join(os.path.dirname(path) or ".", pattern))):
        try:
            state = load_checkpoint(candidate)
            longer = from_dict(state["config"])
        except Exception:  # noqa: BLE001  # not a snapshot this code reads: not a candidate
            continue
        same_length = dataclasses.replace(
            longer, skill=dataclasses.replace(longer.skill, pretrain_steps=steps))
        theirs = json.dumps(snapshot_settings(same_length, state.get("seed", -1)),
                            sort_keys=True, default=str)
        if state.get("steps") != steps or theirs != ours:
            continue
        tmp = f"{path}.{os.getpid()}.tmp"
        shutil.copyfile(candidate, tmp)
        os.replace(tmp, path)
        measured = quality.read(candidate)
        if measured is not None:
            quality.write(path, {k: v for k, v in measured.items()
                                 if k not in ("snapshot", "pretrain_steps")}, steps)
        print(f"{os.path.basename(path)}: the snapshot a longer pretraining with the same "
              f"settings wrote at {steps} steps ({os.path.basename(candidate)})",
              file=sys.stderr, flush=True)
        return path
    return None

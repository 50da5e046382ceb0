"""The agent as the training loop sees it: what it acts on besides the observation, and how it
learns. The loop passes each episode's `EpisodeMeta` along without branching on it (URLB's
`meta`): no skill for SAC, z for S-EPOA's skill-conditioned agent pi(a|s,z); the replay buffer
and the trajectory recorder keep its skill with each transition and trajectory.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from runvocab.config import RunConfig
from runvocab.snapshot_names import snapshot_path, snapshot_seed
from trainer.hooks import RunHooks
from trainer.replay_buffer import ReplayBuffer
from trainer.return_estimator import ReturnEstimator
from trainer.sac import SAC, UpdateMetrics
from trainer.skills import SkillAgent, SkillBackend, SkillReplayBuffer
from trainer.skills.pretrain import build_skill_agent, load_snapshot, pretrain_once
from trainer.utils import set_seed


@dataclass(frozen=True)
class EpisodeMeta:
    """What an episode acts on besides the observation."""

    skill: np.ndarray | None = None
    """S-EPOA's skill z (None for SAC's pi(a|s))"""


Batches = Callable[[], Any]
"""draws a replay batch carrying the reward the agent trains on now"""


class Policy:
    """SAC's pi(a|s): the oracle and the PEBBLE family."""

    estimator: ReturnEstimator | None = None
    """S-EPOA's R_theta(z), which query selection scores skills with"""

    def __init__(self, cfg: RunConfig, obs_dim: int, act_dim: int, device: torch.device):
        self.cfg = cfg
        self._sac = SAC(obs_dim, act_dim, cfg.sac, device)
        self.agent: SAC | SkillAgent = self._sac
        """what the loop resets, checkpoints and restores"""
        self.buffer: ReplayBuffer = ReplayBuffer(obs_dim, act_dim, cfg.replay_capacity,
                                                 device, cfg.seed)

    @property
    def random_seed_steps(self) -> int:
        """Steps of uniformly random actions at the start."""
        return self.cfg.seed_steps

    @property
    def learning_starts(self) -> int:
        """The first step whose update may run (on whatever reward the run has then)."""
        return self.cfg.seed_steps

    free_initial_rollouts = 0
    """episodes played before step 0, uncounted, for the first round (S-EPOA as the authors
    run it)"""

    @property
    def updates_after_first_round(self) -> int:
        """Updates at once after the first round: PEBBLE's reset_update, where the critic was
        reset."""
        return self.cfg.reset_updates if self.resets_critic else 0

    def trajectories_for_first_round(self) -> int:
        return 2

    def episode_meta(self, rng: np.random.Generator) -> EpisodeMeta:
        return EpisodeMeta()

    def eval_meta(self, episode_meta: EpisodeMeta) -> EpisodeMeta:
        """What evaluation episodes act with, given the current episode's."""
        return episode_meta

    def act(self, obs: np.ndarray, meta: EpisodeMeta, rng: np.random.Generator,
            deterministic: bool = False) -> np.ndarray:
        return self._sac.act(obs, rng, deterministic)

    updates = 0
    """SAC gradient updates so far in the online run"""
    reward_updates = 0
    """of those, on the learned reward r_hat (after the first round)"""

    def update(self, batches: Batches, learned: bool) -> UpdateMetrics:
        """One SAC gradient update. Every algorithm makes exactly one per update step, so arms
        compared at equal steps have equal update budgets (`updates` counts them)."""
        metrics = self._gradient_step(batches)
        self.updates += 1
        self.reward_updates += int(learned)
        return metrics

    def _gradient_step(self, batches: Batches) -> UpdateMetrics:
        return self.agent.update(batches())

    def round_closed(self, rng: np.random.Generator) -> dict[str, float]:
        """R_theta was refitted (S-EPOA): nothing to do here, nothing to log."""
        return {}

    @property
    def resets_critic(self) -> bool:
        """At the first round: PEBBLE's critic learned the intrinsic reward (RIME's warm start
        keeps it)."""
        return not self.cfg.reward.rime

    def state_dict(self) -> dict[str, Any]:
        return {"updates": self.updates, "reward_updates": self.reward_updates}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.updates, self.reward_updates = state["updates"], state["reward_updates"]


class SkillPolicy(Policy):
    """S-EPOA's pi(a|s,z) from its pretraining snapshot. Before the first round each episode
    acts with a random skill; then with z_task, the best of N_z random skills under R_theta,
    drawn as each round closes (or at each episode, `skill.task_skill_draw`)."""

    estimator: ReturnEstimator

    def __init__(self, cfg: RunConfig, obs_dim: int, act_dim: int, device: torch.device,
                 hooks: RunHooks):
        self.cfg, self.device = cfg, device
        self._skill_agent, self.skills = _load_skill_agent(cfg, obs_dim, act_dim, device,
                                                           hooks)
        self.agent = self._skill_agent
        self.buffer = SkillReplayBuffer(obs_dim, act_dim, self.skills.skill_dim,
                                        cfg.replay_capacity, device, cfg.seed)
        self.estimator = ReturnEstimator(self.skills.skill_dim, cfg.skill, device)
        self.task_skill: np.ndarray | None = None
        """z_task, from the first round's end on"""
        self._task_skill_copy: tuple[np.ndarray | None, torch.Tensor] | None = None
        """z_task and its copy on the device: one copy per draw, not one per z_task update"""
        self._stored_skill_metrics: UpdateMetrics = {}
        """the last stored-skill update's metrics, logged beside a z_task update's"""

    @property
    def random_seed_steps(self) -> int:
        return 0  # it explores with its pretrained skills from the start

    @property
    def learning_starts(self) -> int:
        return 0  # it updates from the first round on (`update`), whenever that comes

    @property
    def free_initial_rollouts(self) -> int:  # type: ignore[override]
        return self.cfg.skill.initial_rollouts if self.cfg.skill.free_initial_rollouts else 0

    @property
    def updates_after_first_round(self) -> int:
        """After uncounted initial rollouts the authors' code makes these updates whether or
        not the critic was reset."""
        reset_or_free = self.resets_critic or self.cfg.skill.free_initial_rollouts
        return self.cfg.reset_updates if reset_or_free else 0

    def trajectories_for_first_round(self) -> int:
        """Its initial rollouts, each with its own random skill, so round 0 compares many."""
        return max(2, self.cfg.skill.initial_rollouts)

    def episode_meta(self, rng: np.random.Generator) -> EpisodeMeta:
        if self.task_skill is None:
            return EpisodeMeta(self.skills.sample_skills(rng, 1)[0])
        if self.cfg.skill.task_skill_draw == "episode":
            self._draw_task_skill(rng)
        return EpisodeMeta(self.task_skill)

    def eval_meta(self, episode_meta: EpisodeMeta) -> EpisodeMeta:
        """z_task once there is one; before, the current episode's random skill."""
        return episode_meta if self.task_skill is None else EpisodeMeta(self.task_skill)

    def act(self, obs: np.ndarray, meta: EpisodeMeta, rng: np.random.Generator,
            deterministic: bool = False) -> np.ndarray:
        assert meta.skill is not None, "pi(a|s,z) acts with a skill"
        return self._skill_agent.act(obs, meta.skill, rng, deterministic)

    def update(self, batches: Batches, learned: bool) -> UpdateMetrics:
        if not learned:
            return {}  # the pretrained policy stays until there is a reward to learn
        return super().update(batches, learned)

    def _gradient_step(self, batches: Batches) -> UpdateMetrics:
        """The update on the batch's stored skills and the z_task update take turns: one SAC
        update per update step in all, as for every other algorithm (the authors' code runs
        both on every 2nd step: the same budget, less evenly spread)."""
        batch = batches()
        # After uncounted initial rollouts the authors' code makes its first updates before it
        # draws a z_task: on the stored skills alone.
        first = self.updates_after_first_round if self.cfg.skill.free_initial_rollouts else 0
        if not (self.cfg.skill.task_skill_update and self.updates % 2 == 1
                and self.updates >= first):
            self._stored_skill_metrics = self.agent.update(batch)
            return self._stored_skill_metrics
        # The acting skill learns from every transition, not only its own episode's share.
        if self._task_skill_copy is None or self._task_skill_copy[0] is not self.task_skill:
            self._task_skill_copy = (self.task_skill,
                                     torch.as_tensor(self.task_skill, device=self.device))
        task = self._task_skill_copy[1].expand_as(batch.skill)
        task_metrics = self.agent.update(batch._replace(skill=task))
        return self._stored_skill_metrics | {f"task_{k}": v for k, v in task_metrics.items()}

    def round_closed(self, rng: np.random.Generator) -> dict[str, float]:
        """z_task drawn again from R_theta as it now stands (the updates after a critic reset
        train the new one), and how far it moved, for rounds.csv: `task_skill_cosine`, its
        cosine with the z_task before (1: unchanged; NaN at the first round), `task_skill_gain`,
        R_theta(new) - R_theta(before), and `task_skill_predicted`, R_theta(new)."""
        before = self.task_skill
        self._draw_task_skill(rng)
        assert self.task_skill is not None
        skills = [self.task_skill] if before is None else [self.task_skill, before]
        with torch.no_grad():
            new, *old = self.estimator.predict(np.stack(skills)).tolist()
        cosine = gain = math.nan
        if before is not None:
            norms = float(np.linalg.norm(self.task_skill) * np.linalg.norm(before))
            cosine = float(self.task_skill @ before) / norms if norms > 0 else math.nan
            gain = new - old[0]
        return {"task_skill_cosine": cosine, "task_skill_gain": gain,
                "task_skill_predicted": new}

    def _draw_task_skill(self, rng: np.random.Generator) -> None:
        # Not fitted before the second round only where it is fitted only as rounds select
        # (the authors' code): their first z_task is the unfitted R_theta's argmax.
        assert self.estimator.fitted or not self.cfg.skill.estimator_refit
        candidates = self.skills.sample_skills(rng, self.cfg.skill.task_skill_samples)
        self.task_skill = self.estimator.best_skill(candidates)

    @property
    def resets_critic(self) -> bool:
        """Its critic was pretrained on the skills' intrinsic reward (`skill.reset_critic`)."""
        return self.cfg.skill.reset_critic

    def state_dict(self) -> dict[str, Any]:
        return super().state_dict() | {"task_skill": self.task_skill}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        self.task_skill = state["task_skill"]


def make_policy(cfg: RunConfig, obs_dim: int, act_dim: int, device: torch.device,
                hooks: RunHooks) -> Policy:
    if cfg.algo == "sepoa":
        return SkillPolicy(cfg, obs_dim, act_dim, device, hooks)
    return Policy(cfg, obs_dim, act_dim, device)


def _load_skill_agent(cfg: RunConfig, obs_dim: int, act_dim: int, device: torch.device,
                      hooks: RunHooks) -> tuple[SkillAgent, SkillBackend]:
    """pi(a|s,z) from the run's pretraining snapshot (pretrained first when missing), or fresh
    when skill.pretrain_steps is 0."""
    if cfg.skill.pretrain_steps == 0:
        agent, backend = build_skill_agent(cfg, obs_dim, act_dim, device)
        return _online_actor(cfg, agent), backend
    path = snapshot_path(cfg)
    if not os.path.exists(path):
        print(f"no skill snapshot at {path}: pretraining {cfg.skill.backend} for "
              f"{cfg.skill.pretrain_steps} steps first", file=sys.stderr, flush=True)
        # Once per snapshot: other runs needing it (other workers too) wait, heartbeating.
        pretrain_once(dataclasses.replace(cfg, seed=snapshot_seed(cfg)), path,
                      tick=hooks.pretraining, waiting=hooks.waiting_for_snapshot)
        set_seed(cfg.seed)  # the online run starts from the same state as with a snapshot at hand
    snapshot = load_snapshot(path, cfg.task, cfg.skill.backend)
    agent, backend = build_skill_agent(cfg, obs_dim, act_dim, device, snapshot)
    return _online_actor(cfg, agent), backend


DDPG_ALPHA = 1.0
"""the temperature the authors' fine-tuning starts from (not the snapshot's), then tunes"""


def _online_actor(cfg: RunConfig, agent: SkillAgent) -> SkillAgent:
    """The agent with the actor fine-tuning uses (`skill.actor`)."""
    if cfg.skill.actor == "ddpg":
        agent.sac.fix_actor_std(cfg.skill.actor_std, cfg.skill.actor_clip, DDPG_ALPHA)
    return agent

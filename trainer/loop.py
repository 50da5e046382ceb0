"""The training loop: SAC on the ground-truth reward (the oracle), PEBBLE, or S-EPOA.

PEBBLE: `seed_steps` of random actions, then unsupervised state-entropy pretraining until the
first feedback round, a critic reset after that round, then a round every `feedback.every` steps
until the label budget is spent. SURF, RUNE and RIME are PEBBLE with one piece added, switched
on by their algorithm presets (`reward.surf`, `reward.rune`, `reward.rime`):
- SURF: cropped segments and pseudo-labels in reward training (trainer/surf.py).
- RUNE: the agent trains on r_hat + beta_t * (the ensemble's std of r_hat), with
  beta_t = beta_0 (1 - rho)^t where t counts environment steps since the first round closed,
  i.e. since the agent began training on r_hat. The bonus is computed per update batch from the
  current model and beta_t, so relabelling the buffer never freezes an old beta into it.
- RIME: the label filter (trainer/rime.py), and a reward model warm-started on the normalised
  state-entropy reward during the unsupervised phase, so the critic is kept, not reset, after
  the first round.

S-EPOA (Algorithm 1): the skill-conditioned actor and critic pi(a|s,z) start from a pretraining
snapshot (`sepoa pretrain`; made first if missing, or fresh nets when skill.pretrain_steps is 0,
the paper's "no pretraining" ablation). Each episode acts with one skill: a random one until the
first round, then z_task, the best of N_z fresh random skills under R_theta, drawn when a round
refits R_theta and held until the next (or drawn each episode: skill.task_skill_draw). The
first round comes after `seed_steps` and `skill.initial_rollouts` episodes; the agent trains
only on the learned reward, from the first round on, where its pretrained critic is reset
(skill.reset_critic). Its updates take turns: one trains the batch's stored skills, the next,
with z_task in every row, the acting skill (skill.task_skill_update). Every algorithm makes one
SAC update per update step (`update_every`), so arms compared at equal steps have equal update
budgets; episodes.csv counts them (`updates`, and `reward_updates` on r_hat). Queries are
selected by the skill rule, each the best of its own candidates (query_selection.py).

After any critic reset, `reset_updates` updates on the relabelled buffer follow at once
(PEBBLE's reset_update). S-EPOA can also run as its authors' code does (docs/SEPOA.md): with
`skill.free_initial_rollouts` its initial rollouts are played on the evaluation env before
step 0, uncounted, the first round opens at once and the agent learns from step 0.

`reward.true_reward` is a diagnostic: the rounds keep their schedule but ask nothing
(trainer/true_reward_rounds.py) and the agent trains on the environment's reward.

Rounds, evaluations and checkpoints happen at episode boundaries, so a checkpoint never has to
capture a half-run episode; the one thing a checkpoint cannot wait for, a round's reward
training, saves its own progress beside it (`round_progress.py`). The loop itself does not
branch on the algorithm: the reward the agent trains on is `agent_reward.py`'s, and how the
agent acts and learns (S-EPOA's skills included) is `policies.py`'s.
"""

from __future__ import annotations

import os
import time

import numpy as np
import torch
from tqdm import tqdm  # type: ignore[import-untyped]

from runvocab.config import RunConfig, save_json
from runvocab.validate import validate
from trainer.agent_reward import make_agent_reward
from trainer.checkpoint import (
    load_checkpoint,
    random_state,
    restore_random_state,
    save_checkpoint,
)
from trainer.envs import make_env
from trainer.feedback import Feedback, GivenAnswer, LabelLog, NoFeedback, PreferenceFeedback
from trainer.hooks import RunHooks
from trainer.metrics import Metrics
from trainer.phase_clock import PhaseClock
from trainer.policies import EpisodeMeta, make_policy
from trainer.replay_buffer import Batch
from trainer.return_estimator import ReplayEpisodes
from trainer.reward_model import RewardModel
from trainer.round_progress import ROUND_PROGRESS, RoundLeft, RoundProgress
from trainer.sac import UpdateMetrics
from trainer.schedule import After, Every, Period, Until
from trainer.skills import SkillReplayBuffer
from trainer.teachers import make_teacher
from trainer.trajectories import EpisodeRecorder, TrajectoryPool
from trainer.true_reward_rounds import TrueRewardRounds
from trainer.utils import pick_device, set_seed

CHECKPOINT = "checkpoint.pt"
LOOP_VERSION = 3
"""Checkpoints of version 1 predate S-EPOA's initial rollouts, per-query selection, z_task
updates and critic reset, and PEBBLE's post-reset updates; those of version 2, S-EPOA's one
update per step (its two updates took two per step) and the update counts. Such a run cannot
resume as it began, so it is refused."""
RESUMABLE_FROM = {1: ("sac",), 2: ("sac", "pebble", "surf", "rune", "rime")}
"""older loop versions, and the algorithms whose runs they still resume"""


def default_run_dir(cfg: RunConfig) -> str:
    return os.path.join("runs", f"{cfg.task.replace(':', '-')}-{cfg.algo}-s{cfg.seed}")


class TrainingRun:
    def __init__(self, cfg: RunConfig, resume: bool = False, progress: bool = True,
                 hooks: RunHooks | None = None):
        validate(cfg)
        self.cfg, self.progress = cfg, progress
        self.hooks = hooks or RunHooks()
        self.run_dir = cfg.run_dir or default_run_dir(cfg)
        self.checkpoint_path = os.path.join(self.run_dir, CHECKPOINT)
        if not resume and os.path.exists(self.checkpoint_path):
            raise FileExistsError(
                f"{self.run_dir} already holds a run; pass --resume to continue it "
                "or choose another --run-dir"
            )
        if resume and not os.path.exists(self.checkpoint_path):
            raise FileNotFoundError(f"--resume: no checkpoint in {self.run_dir}")
        os.makedirs(self.run_dir, exist_ok=True)

        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        set_seed(cfg.seed)
        self.device = pick_device(cfg.device)
        length = cfg.episode_length or None
        self.env = make_env(cfg.task, cfg.seed, length)
        self.eval_env = make_env(cfg.task, cfg.seed + 100_000, length)
        obs_dim, act_dim = self.env.obs_dim, self.env.action_dim
        self.rng = np.random.default_rng(cfg.seed)
        self.policy = make_policy(cfg, obs_dim, act_dim, self.device, self.hooks)
        self.agent, self.buffer = self.policy.agent, self.policy.buffer
        self.meta = EpisodeMeta()
        """what the current episode acts on besides the observation (S-EPOA: its skill)"""
        self.pool = TrajectoryPool(cfg.feedback.pool_trajectories)
        self.env.reset()
        state_dim = len(self.env.physics_state())
        self.recorder = EpisodeRecorder(obs_dim, act_dim, state_dim, self.env.episode_length)

        self.feedback: Feedback = NoFeedback()
        if cfg.reward.true_reward:
            self.feedback = TrueRewardRounds(cfg.feedback, self.policy.estimator,
                                             self._replay_episodes())
        elif cfg.algo != "sac":
            model = RewardModel(obs_dim, act_dim, cfg.reward, self.device, cfg.seed)
            teacher = make_teacher(cfg.teacher, cfg.seed, cfg.feedback.segment_length,
                                   self.env.episode_length)
            self.feedback = PreferenceFeedback(
                cfg.feedback, model, teacher, f"scripted:{cfg.teacher.kind}",
                LabelLog(os.path.join(self.run_dir, "labels.jsonl")),
                np.random.default_rng(cfg.seed + 1), self.policy.estimator,
                cfg.skill.score_spread, self._replay_episodes(), cfg.skill.estimator_refit,
            )

        self.step = 0
        self.episode = 0
        self.stopped = False
        self.reward = make_agent_reward(cfg, self.buffer, self.feedback, self.device)
        self.next_round_step = cfg.seed_steps + self.reward.unsupervised_steps
        self.random_actions = Until(self.policy.random_seed_steps)
        self.learning = After(self.policy.learning_starts)
        self.update_step = Every(cfg.update_every)
        self.evaluations = Period(cfg.eval_every)
        self.checkpoints = Period(max(cfg.checkpoint_every, 1))  # 0: at every episode's end
        self.round_progress = RoundProgress(os.path.join(self.run_dir, ROUND_PROGRESS))
        """the open round's reward training, saved as it goes (trainer/round_progress.py)"""
        if not resume:
            self.round_progress.clear()
        if resume:
            self._load()
        else:
            save_json(cfg, os.path.join(self.run_dir, "config.json"))
        self.metrics = Metrics(self.run_dir, purge_step=self.step + 1 if resume else None)
        self.clock = PhaseClock()
        """where the wall time goes, written with every episode row"""
        if resume:
            self._trim_metrics()

    def _replay_episodes(self) -> ReplayEpisodes | None:
        """R_theta's data when it is fitted on the replay buffer (`skill.estimator_data`)."""
        if self.policy.estimator is None or self.cfg.skill.estimator_data != "replay":
            return None
        assert isinstance(self.buffer, SkillReplayBuffer)  # a policy with R_theta has skills
        return ReplayEpisodes(self.buffer, self.env.episode_length)

    # ----------------------------------------------------------------------------------------
    def _start_episode(self) -> np.ndarray:
        """Reset the env, then the episode's meta (the reset and the pick happen in this order
        in an uninterrupted run and in a resumed one alike)."""
        obs = self.env.reset()
        self.meta = self.policy.episode_meta(self.rng)
        return obs

    def _update(self) -> UpdateMetrics:
        return self.policy.update(self._training_batch, self.reward.learned)

    def _training_batch(self) -> Batch:
        return self.reward.batch(self.buffer.sample(self.cfg.sac.batch_size), self.step)

    def _log(self, stream: str, row: dict) -> None:
        self.metrics.log(stream, row)
        self.hooks.metrics(stream, row)

    def train(self) -> dict[str, float]:
        """Train until `cfg.steps`, or until the hooks ask to stop: at an episode's end, after a
        checkpoint (`summary()["stopped"]` is 1), or, asked inside a round's reward training, at
        once, that training saved beside the checkpoint written as the round opened (the
        summary's `round_epochs_saved` says how far it got)."""
        try:
            return self._train()
        except RoundLeft as left:
            self.stopped = True
            self.metrics.close()
            return self.summary() | {"round_epochs_saved": left.epochs}

    def next_round_at(self) -> int:
        """The step the next round opens at: the first episode end at or past
        `next_round_step` (episodes have a fixed length)."""
        length = self.env.episode_length
        return -(-self.next_round_step // length) * length

    def _train(self) -> dict[str, float]:
        cfg, feedback = self.cfg, self.feedback
        self.hooks.started(self.step, self.next_round_at)
        if feedback.pending:  # resumed inside a round
            self.hooks.round_opened(feedback.pending, self.pool)
            self._try_finish_round()
        if self.step == 0 and self.episode == 0 and self.policy.free_initial_rollouts:
            self._free_initial_rollouts()
            self.next_round_step = 0
            self._open_round()
        obs = self._start_episode()
        episode_return, last_metrics = 0.0, {}  # the last update's, read as an episode ends
        stopping = False
        start_step, start_time = self.step, time.time()
        bar = tqdm(total=cfg.steps, initial=self.step, disable=not self.progress,
                   dynamic_ncols=True, unit="step")
        seconds = self.clock.seconds
        while self.step < cfg.steps:
            tick = time.perf_counter()
            if self.random_actions(self.step):
                action = self.rng.uniform(-1, 1, self.env.action_dim).astype(np.float32)
            else:
                action = self.policy.act(obs, self.meta, self.rng).astype(np.float32)
            acted = time.perf_counter()
            # The update comes between the action and the environment's step, as in the
            # authors' loops (URLB's, pytorch_sac's): on a GPU it runs while the host steps
            # the simulator. It trains on the transitions before this one (none yet at the
            # first step of a run with `seed_steps` 0, which therefore skips that update).
            made = self.step + 1
            if self.learning(made) and self.update_step(made) and len(self.buffer):
                last_metrics = self._update()
            updated = time.perf_counter()
            state = self.env.physics_state()
            result = self.env.step(action)
            reward = self.reward.at_step(obs, action, result.reward)
            self.buffer.add(obs, action, reward, result.reward, result.obs, self.meta.skill)
            self.recorder.record(obs, action, result.reward, state, result.success)
            obs, episode_return = result.obs, episode_return + result.reward
            self.step = made
            seconds["acting"] += (acted - tick) + (time.perf_counter() - updated)
            seconds["updates"] += updated - acted
            bar.update(1)
            stopping = stopping or self.hooks.stop_requested(self.step)

            if result.done:
                traj = self.recorder.finish(self.episode, self.env.episode_context(),
                                            self.meta.skill)
                self.pool.add(traj)
                self.episode += 1
                self.hooks.episode_ended(traj.id, self.env.physics_state())
                fps = (self.step - start_step) / max(time.time() - start_time, 1e-9)
                self._log("episodes", {
                    "step": self.step, "episode": self.episode, "return": episode_return,
                    "success": float(traj.success), "labels_used": feedback.labels_used,
                    "updates": self.policy.updates, "reward_updates": self.policy.reward_updates,
                    "fps": fps,
                } | {k: float(v) for k, v in last_metrics.items()
                     if k in ("critic_loss", "alpha", "q")}
                  | self.reward.episode_row(self.step) | self.clock.row())
                seconds = self.clock.seconds
                self._end_of_episode()
                bar.set_postfix(ret=f"{episode_return:.1f}",
                                labels=feedback.labels_used, refresh=False)
                if stopping or self.hooks.stop_requested(self.step):
                    self.stopped = True  # before the reset: a resumed run makes that reset
                    break
                obs, episode_return = self._start_episode(), 0.0
        bar.close()
        if feedback.pending and not self.stopped:
            self._try_finish_round()  # a round still collecting answers closes with what came
        self._save()
        self.metrics.close()
        return self.summary()

    def _end_of_episode(self) -> None:
        cfg = self.cfg
        if self.evaluations.due(self.step):
            with self.clock("evaluation"):
                self.evaluate()
        if self.feedback.pending:
            self._try_finish_round()
        # No round at the very end: its labels could no longer shape the policy.
        elif self.next_round_step <= self.step < cfg.steps:
            self._open_round()
        if self.checkpoints.due(self.step):
            self._save()

    def _open_round(self) -> None:
        """Open a round where the budget and the pool allow one."""
        if self.feedback.budget_left <= 0 or len(self.pool) < self._pool_needed():
            return
        fb = self._preferences()
        if isinstance(fb, TrueRewardRounds):  # nothing to select or answer
            self._finish_round({})
            self._save()
            return
        with self.clock("selection"):
            fb.open_round(self.pool, self.step)
        self._save()  # the chosen queries survive a kill; their answers go to labels.jsonl
        self.hooks.round_opened(fb.pending, self.pool)
        self._try_finish_round()

    def _free_initial_rollouts(self) -> None:
        """S-EPOA as the authors run it: episodes of random skills on the evaluation env
        before step 0, uncounted, stored in the replay buffer and the pool for the first
        round."""
        env = self.eval_env
        for _ in range(self.policy.free_initial_rollouts):
            obs, done = env.reset(), False
            meta = self.policy.episode_meta(self.rng)
            while not done:
                action = self.policy.act(obs, meta, self.rng).astype(np.float32)
                state = env.physics_state()
                result = env.step(action)
                reward = self.reward.at_step(obs, action, result.reward)
                self.buffer.add(obs, action, reward, result.reward, result.obs, meta.skill)
                self.recorder.record(obs, action, result.reward, state, result.success)
                obs, done = result.obs, result.done
            self.pool.add(self.recorder.finish(self.episode, env.episode_context(), meta.skill))
            self.episode += 1

    def _preferences(self) -> PreferenceFeedback | TrueRewardRounds:
        """The run's feedback where a round opens or closes: only a preference run's (or its
        true-reward diagnostic's) ever does (the SAC oracle's budget is 0)."""
        assert isinstance(self.feedback, PreferenceFeedback | TrueRewardRounds)
        return self.feedback

    def _pool_needed(self) -> int:
        """Trajectories a round needs: two, and for the first round the policy's say (S-EPOA:
        its initial rollouts, so the first labels compare many skills)."""
        return self.policy.trajectories_for_first_round() if self.feedback.rounds == 0 else 2

    def _try_finish_round(self) -> None:
        """Finish the open round if its answers are in; it must close once the next round is
        due, or at the end of the run."""
        fb = self._preferences()
        assert isinstance(fb, PreferenceFeedback) and fb.pending
        due = min(fb.pending[0].step + self.cfg.feedback.every, self.cfg.steps)
        with self.clock("waiting"):
            answers = self.hooks.answers(fb, self.pool, final=self.step >= due)
        if answers is not None:
            self._finish_round(answers)
            # Saved at once: the round's reward training is minutes of CPU (45 under load) that
            # a kill before the next checkpoint would throw away; and a round that closed
            # episodes after it opened must not be re-lived, its wait having depended on when
            # people answered.
            self._save()
            self.round_progress.clear()

    def _finish_round(self, answers: dict[str, GivenAnswer]) -> None:
        fb = self._preferences()
        first = fb.rounds == 0
        start = time.perf_counter()
        metrics = fb.finish_round(self.pool, answers,
                                  after_epoch=lambda: self.hooks.reward_epoch(self.step),
                                  progress=self.round_progress)
        fb.relabel(self.buffer)
        metrics["reward_corr"] = self.buffer.reward_correlation()
        metrics |= self.policy.round_closed(self.rng)
        estimator = metrics.get("estimator_seconds", 0.0)
        self.clock.add("estimator", estimator)
        self.clock.add("reward_training", time.perf_counter() - start - estimator)
        if first:
            self.reward.first_round_closed(self.step)
            if self.policy.resets_critic:
                self.agent.reset_critic()
            # PEBBLE's reset_update: a fresh critic catches up on the learned reward.
            with self.clock("updates"):
                for _ in range(self.policy.updates_after_first_round):
                    self._update()
        self.next_round_step = self.step + self.cfg.feedback.every
        self._log("rounds", {"step": self.step} | metrics)

    def evaluate(self) -> dict[str, float]:
        """Deterministic episodes on the evaluation env; S-EPOA acts with z_task once it has
        one."""
        returns, successes = [], []
        for _ in range(self.cfg.eval_episodes):
            obs, total, success, done = self.eval_env.reset(), 0.0, False, False
            while not done:
                action = self.policy.act(obs, self.policy.eval_meta(self.meta), self.rng, True)
                result = self.eval_env.step(action)
                obs, total, success, done = (result.obs, total + result.reward,
                                             success or result.success, result.done)
            returns.append(total)
            successes.append(success)
        self.evaluations.happened(self.step)
        row = {"step": self.step, "return": float(np.mean(returns)),
               "return_std": float(np.std(returns)), "success_rate": float(np.mean(successes)),
               "labels_used": self.feedback.labels_used}
        self._log("eval", row)
        return row

    def summary(self) -> dict[str, float]:
        returns = self.pool.returns[-10:]
        out = {"step": self.step, "episodes": self.episode, "stopped": int(self.stopped),
               "updates": self.policy.updates, "reward_updates": self.policy.reward_updates,
               "mean_return_last10": float(np.mean(returns)) if returns else float("nan")}
        return out | self.feedback.summary()

    # ----------------------------------------------------------------------------------------
    def _state(self) -> dict:
        state = self.policy.state_dict() | self.reward.state_dict() | {
            "loop_version": LOOP_VERSION,
            "step": self.step,
            "episode": self.episode,
            "next_round_step": self.next_round_step,
            "last_eval_step": self.evaluations.last,
            "agent": self.agent.state_dict(),
            "buffer": self.buffer.state_dict(),
            "pool": self.pool.state_dict(),
            "env_rng": self.env.rng_state(),
            "eval_env_rng": self.eval_env.rng_state(),
        } | random_state(self.rng, self.device)
        # No feedback section in a SAC run's checkpoint: reward_fit reads that as "no reward
        # model".
        if feedback := self.feedback.state_dict():
            state["feedback"] = feedback
        return state

    def _save(self) -> None:
        self.checkpoints.happened(self.step)
        with self.clock("checkpoints"):
            save_checkpoint(self.checkpoint_path, self._state())

    def _load(self) -> None:
        state = load_checkpoint(self.checkpoint_path)
        version = state.get("loop_version", 1)
        if version != LOOP_VERSION and self.cfg.algo not in RESUMABLE_FROM.get(version, ()):
            raise ValueError(
                f"{self.checkpoint_path} was written by training-loop version {version}; this "
                f"is version {LOOP_VERSION}, whose {self.cfg.algo} differs (S-EPOA's initial "
                "rollouts, per-query selection, z_task updates, critic reset and one update "
                "per step; the updates after a critic reset), so the run cannot resume as it "
                "began: start a new run")
        # Update counts are logged since version 3; older runs resume counting from 0.
        self.policy.load_state_dict({"updates": 0, "reward_updates": 0} | state)
        self.step, self.episode = state["step"], state["episode"]
        self.next_round_step = state["next_round_step"]
        self.evaluations.happened(state["last_eval_step"])
        self.reward.load_state_dict(state)
        self.checkpoints.happened(self.step)
        self.agent.load_state_dict(state["agent"])
        self.buffer.load_state_dict(state["buffer"])
        self.pool.load_state_dict(state["pool"])
        restore_random_state(state, self.rng, self.device)
        self.env.set_rng_state(state["env_rng"])
        self.eval_env.set_rng_state(state["eval_env_rng"])
        self.feedback.load_state_dict(state.get("feedback", {}))

    def _trim_metrics(self) -> None:
        """Drop metric rows written after the checkpoint; the resumed run writes them again."""
        step = self.step
        pending = bool(self.feedback.pending)
        self.metrics.streams["episodes"].keep_rows(lambda r: int(r["step"]) <= step)
        self.metrics.streams["eval"].keep_rows(lambda r: int(r["step"]) <= step)
        self.metrics.streams["rounds"].keep_rows(
            lambda r: int(r["step"]) < step or (int(r["step"]) == step and not pending)
        )

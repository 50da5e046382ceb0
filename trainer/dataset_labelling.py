"""A labelling-only run: rounds of pairs drawn from an existing dataset's episodes, no training.

The worker serves a run made by `rundata.labelling.create_labelling_run` with this instead
of `trainer.loop.TrainingRun`, through the same hooks (`trainer.queue_hooks.QueueHooks`): each round
is opened by `PreferenceFeedback` on a pool that holds every episode of the dataset (uniformly
for the first round, then by the run's `feedback.selection`: the disagreement of the reward
ensemble refitted on every label so far), pushed to the queue with its clips rendered from the
episodes' stored physics states, answered by people or the scripted teacher (which judges by the
dataset's true rewards), and closed, which refits the ensemble. Rounds follow one another until
the budget is spent; then the run finishes. A trajectory's id is its episode's id in the dataset,
so every query and label points at the dataset's episodes.

The run's folder holds what a training run's does for its labels: `config.json`,
`labels.jsonl`, `rounds.csv` and `checkpoint.pt` (the feedback state: the labelled pairs, the
ensemble, the open round), written as each round opens and closes, so a worker that takes the
run over resumes the open round. Its `step` counts the rounds closed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rundata.dataset import EPISODES_FILE, LabelledDataset, read_dataset
from rundata.episodes import end_path, write_end_state
from runvocab.config import RunConfig, save_json
from trainer.checkpoint import load_checkpoint, save_checkpoint
from trainer.envs import make_env
from trainer.feedback import LabelLog, PreferenceFeedback
from trainer.hooks import RunHooks
from trainer.metrics import Metrics
from trainer.reward_model import RewardModel
from trainer.teachers import make_teacher
from trainer.trajectories import Trajectory, TrajectoryPool
from trainer.utils import pick_device, set_seed

CHECKPOINT = "checkpoint.pt"
STATE_FORMAT = "sepoa.dataset_labelling"


class DatasetLabelling:
    """Serves a labelling run's rounds over `dataset` (a dataset export's folder) until its
    budget is spent or the hooks ask it to stop. `episode_store`: the run's episode store
    (`rundata.episodes`); each episode's final state is kept there, so the episodes the
    run's queries point into are stored as exactly as a training run stores its own."""

    def __init__(self, cfg: RunConfig, dataset: str, *, resume: bool = False,
                 hooks: RunHooks | None = None, episode_store: Path | None = None):
        self.cfg, self.hooks = cfg, hooks or RunHooks()
        self.dataset = read_dataset(dataset)
        self.pool = dataset_pool(self.dataset, cfg.task)
        self.run_dir = cfg.run_dir
        os.makedirs(self.run_dir, exist_ok=True)
        self.checkpoint_path = os.path.join(self.run_dir, CHECKPOINT)
        if cfg.threads > 0:
            torch.set_num_threads(cfg.threads)
        set_seed(cfg.seed)
        obs_dim = self.dataset.episodes[0].observations.shape[1]
        action_dim = self.dataset.episodes[0].actions.shape[1]
        longest = max(e.length for e in self.dataset.episodes)
        model = RewardModel(obs_dim, action_dim, cfg.reward, pick_device(cfg.device), cfg.seed)
        teacher = make_teacher(cfg.teacher, cfg.seed, cfg.feedback.segment_length, longest)
        self.feedback = PreferenceFeedback(
            cfg.feedback, model, teacher, f"scripted:{cfg.teacher.kind}",
            LabelLog(os.path.join(self.run_dir, "labels.jsonl")),
            np.random.default_rng(cfg.seed + 1))
        self.step = 0
        """the rounds closed"""
        self.stopped = False
        if episode_store is not None:
            for t, e in zip(self.pool.trajectories, self.dataset.episodes, strict=True):
                if not end_path(episode_store, t.id).is_file():
                    write_end_state(episode_store, t.id, e.states[-1])
        if resume:
            self._load()
        else:
            save_json(cfg, os.path.join(self.run_dir, "config.json"))
        self.metrics = Metrics(self.run_dir, purge_step=self.step + 1 if resume else None)
        if resume:  # rows written after the checkpoint are written again
            self.metrics.streams["rounds"].keep_rows(lambda r: int(r["step"]) <= self.step)

    def train(self) -> dict[str, float]:
        """Open, wait for and close rounds until the budget is spent (or a stop); the summary."""
        fb, hooks = self.feedback, self.hooks
        hooks.started(self.step, None)
        if fb.pending:  # resumed inside a round
            hooks.round_opened(fb.pending, self.pool)
        while fb.pending or fb.budget_left > 0:
            if not fb.pending:
                if hooks.stop_requested(self.step):
                    self.stopped = True
                    break
                fb.open_round(self.pool, self.step)
                self._save()  # the chosen pairs survive a kill; their answers go to the queue
                hooks.round_opened(fb.pending, self.pool)
            answers = hooks.answers(fb, self.pool, final=False)
            if answers is None:  # only a stop ends the wait: nothing trains meanwhile
                self.stopped = True
                break
            row = fb.finish_round(self.pool, answers)
            self.step += 1
            row = {"step": self.step} | row
            self.metrics.log("rounds", row)
            hooks.metrics("rounds", row)
            self._save()
        self._save()
        self.metrics.close()
        return self.summary()

    def summary(self) -> dict[str, float]:
        return {"step": self.step, "episodes": len(self.pool), "stopped": int(self.stopped),
                "labels_used": self.feedback.labels_used, "rounds": self.feedback.rounds}

    def _state(self) -> dict[str, Any]:
        return {"format": STATE_FORMAT, "step": self.step,
                "episode_lengths": [t.length for t in self.pool.trajectories],
                "feedback": self.feedback.state_dict(), "torch_rng": torch.get_rng_state()}

    def _save(self) -> None:
        save_checkpoint(self.checkpoint_path, self._state())

    def _load(self) -> None:
        state = load_checkpoint(self.checkpoint_path)
        if state.get("format") != STATE_FORMAT:
            raise ValueError(f"{self.checkpoint_path} is not a labelling run's checkpoint")
        if state["episode_lengths"] != [t.length for t in self.pool.trajectories]:
            raise ValueError(f"{self.dataset.path} changed since the run began: its episodes "
                             "are not those its labels point into")
        self.step = state["step"]
        self.feedback.load_state_dict(state["feedback"])
        torch.set_rng_state(state["torch_rng"])


def dataset_pool(dataset: LabelledDataset, task: str) -> TrajectoryPool:
    """Every episode of `dataset` as a trajectory whose id is its episode id; ValueError when
    the dataset is not of `task`, or its observations, actions or physics states do not fit
    the task's."""
    if dataset.task != task:
        raise ValueError(f"{dataset.path} holds {dataset.task} episodes, not {task}")
    first = dataset.episodes[0]
    have = (first.observations.shape[1], first.actions.shape[1], first.states.shape[1])
    with make_env(task, 0) as env:
        env.reset()
        want = (env.obs_dim, env.action_dim, len(env.physics_state()))
    if have != want:
        raise ValueError(f"{dataset.path}: observations of {have[0]}, actions of {have[1]} and "
                         f"physics states of {have[2]} values; {task} has {want[0]}, "
                         f"{want[1]} and {want[2]}")
    success = _successes(dataset)
    pool = TrajectoryPool(len(dataset.episodes))
    for i, e in enumerate(dataset.episodes):
        pool.add(Trajectory(id=i, obs=e.observations[:-1], actions=e.actions,
                            true_rewards=e.rewards, states=e.states[:-1], context=e.context,
                            success=success.get(i, False)))
    return pool


def _successes(dataset: LabelledDataset) -> dict[int, bool]:
    """Each episode's success as the export recorded it (none: not recorded)."""
    path = Path(dataset.path) / EPISODES_FILE
    if not path.is_file():
        return {}
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    table = pq.read_table(path, columns=["episode_id", "success"]).to_pydict()
    return {int(i): bool(s) for i, s in zip(table["episode_id"], table["success"], strict=True)}

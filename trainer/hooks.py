"""What a supervisor plugs into a training run: stop requests, metrics, and who answers queries.

`TrainingRun` calls these at fixed points; the defaults run it standalone (never stop, keep
metrics in files only, answer each round at once with the run's scripted teacher). The queue
hooks (`trainer.queue_hooks`) override them to obey operators, mirror metrics into the database,
keep episodes and take answers from labellers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from trainer.feedback import GivenAnswer, PreferenceFeedback, Query
from trainer.trajectories import TrajectoryPool


class RunHooks:
    def started(self, step: int, next_round_at: Callable[[], int] | None) -> None:
        """The run starts training at `step` (a resumed run's, or 0). `next_round_at` reads the
        step at which its next round opens (the loop's schedule; None where rounds follow one
        another without steps in between)."""

    def stop_requested(self, step: int) -> bool:
        """Called between steps (keep it cheap). True: end the run at the end of this episode,
        after a checkpoint. May block, e.g. while an operator has the run paused."""
        return False

    def pretraining(self, step: int) -> bool:
        """Called after each step of the skill pretraining an S-EPOA run does first when its
        snapshot is missing (keep it cheap). True: leave the pretraining at the end of this
        episode, its progress saved (`trainer.skills.pretrain.PretrainingLeft`)."""
        return False

    def waiting_for_snapshot(self) -> None:
        """Called about every second while another process pretrains the snapshot this run
        needs (keep it cheap); may raise to leave, as nothing of this run's is to save."""

    def reward_epoch(self, step: int) -> bool:
        """Called after each epoch of a round's reward-model training, which can take many
        minutes on a CPU with SURF (keep it cheap). True: leave the run now, its round's
        training saved (`round_progress.RoundLeft`), rather than at the end of an episode the
        round would first have to finish."""
        return False

    def episode_ended(self, episode: int, end_state: np.ndarray) -> None:
        """The episode (the trajectory of that id) ended in `end_state`, the env's physics state
        after its last step; called before its metric row is logged (keep it cheap)."""

    def metrics(self, stream: str, row: dict[str, Any]) -> None:
        """A metric row the run just logged (stream: episodes | eval | rounds)."""

    def round_opened(self, queries: list[Query], pool: TrajectoryPool) -> None:
        """A round's queries were chosen and checkpointed; also called again for the open round
        of a resumed run."""

    def answers(self, feedback: PreferenceFeedback, pool: TrajectoryPool,
                final: bool) -> dict[str, GivenAnswer] | None:
        """The open round's answers by query id, or None to keep training and ask again at the
        next episode's end. `final`: the round must close now, with whatever answers exist."""
        return feedback.scripted_answers()

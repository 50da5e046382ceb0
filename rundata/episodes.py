"""A run's episode store: the episodes its queries point into, with every step's physics state.

The worker keeps them beside the run's clips, `<clips folder>/run-<id>/episodes/`, because that
folder is the store both the trainer and the server reach (one machine's data folder, or a
shared volume): the dataset export (`rundata.dataset`) reads them there. Files:

- `episode-<n>.npz`: trajectory n of the run (its running episode number), written when a
  round first puts one of its segments to labellers (a query or a gold pair), before the
  queries reach the queue, so every stored query's episodes are on disk;
- `end-<n>.npz`: the physics state after trajectory n's last step, written as each episode ends
  (a few hundred bytes), from which the episode's final observation is restored exactly.

Each file is written under a temporary name and renamed, so a reader never sees half a file.
NumPy only: the server and the trainer both read it.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

EPISODE_RE = re.compile(r"episode-(\d+)\.npz")


def episodes_dir(clips_root: Path | str, run_id: int) -> Path:
    """The folder of run `run_id`'s stored episodes."""
    return Path(clips_root) / f"run-{run_id}" / "episodes"


@dataclass(frozen=True)
class StoredEpisode:
    """One finished episode of a run, as Minari lays an episode out: T actions and rewards,
    T + 1 observations and states (the last one after the final step)."""

    trajectory: int
    """the run's running episode number (a query's `first_trajectory`/`second_trajectory`)"""
    observations: np.ndarray
    """(T + 1, obs_dim) float32"""
    actions: np.ndarray
    """(T, action_dim) float32, each in [-1, 1]"""
    rewards: np.ndarray
    """(T,) float32 ground-truth rewards"""
    states: np.ndarray
    """(T + 1, state_dim) float64 physics state at each observation (trainer.envs.restore)"""
    context: int
    """what the state needs besides itself (Metaworld's goal variant; 0 for DMC)"""
    success: bool
    """Metaworld: success at any step"""
    skill: np.ndarray | None = None
    """the skill vector that acted (skill-based methods), else None"""
    final_resimulated: bool = False
    """the final observation and state were recomputed by stepping the last stored state with
    the last action (an episode that ended before the worker kept end states)"""

    @property
    def length(self) -> int:
        return len(self.rewards)


def _atomic_savez(path: Path, **arrays: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)  # type: ignore[arg-type]
    os.replace(tmp, path)


def episode_path(folder: Path, trajectory: int) -> Path:
    return folder / f"episode-{trajectory}.npz"


def end_path(folder: Path, trajectory: int) -> Path:
    return folder / f"end-{trajectory}.npz"


def write_end_state(folder: Path, trajectory: int, state: np.ndarray) -> None:
    """The physics state after trajectory `trajectory`'s last step."""
    _atomic_savez(end_path(folder, trajectory), state=np.asarray(state, np.float64))


def read_end_state(folder: Path, trajectory: int) -> np.ndarray | None:
    path = end_path(folder, trajectory)
    if not path.is_file():
        return None
    with np.load(path) as data:
        return np.asarray(data["state"])


def write_episode(folder: Path, episode: StoredEpisode) -> None:
    arrays: dict[str, np.ndarray] = {
        "observations": np.asarray(episode.observations, np.float32),
        "actions": np.asarray(episode.actions, np.float32),
        "rewards": np.asarray(episode.rewards, np.float32),
        "states": np.asarray(episode.states, np.float64),
        "context": np.asarray(episode.context, np.int64),
        "success": np.asarray(episode.success),
        "final_resimulated": np.asarray(episode.final_resimulated),
    }
    if episode.skill is not None:
        arrays["skill"] = np.asarray(episode.skill, np.float32)
    _atomic_savez(episode_path(folder, episode.trajectory), **arrays)


def read_episode(folder: Path, trajectory: int) -> StoredEpisode:
    with np.load(episode_path(folder, trajectory)) as data:
        return StoredEpisode(
            trajectory=trajectory,
            observations=data["observations"],
            actions=data["actions"],
            rewards=data["rewards"],
            states=data["states"],
            context=int(data["context"]),
            success=bool(data["success"]),
            skill=data["skill"] if "skill" in data else None,
            final_resimulated=bool(data["final_resimulated"]),
        )


def stored_trajectories(folder: Path) -> list[int]:
    """The trajectory numbers stored in `folder`, ascending (none when it does not exist)."""
    if not folder.is_dir():
        return []
    found = (EPISODE_RE.fullmatch(name) for name in os.listdir(folder))
    return sorted(int(m.group(1)) for m in found if m)

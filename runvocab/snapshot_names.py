"""The file names of S-EPOA's skill snapshots: which snapshot an online run starts from, where
an unfinished pretraining keeps its state, where a pretraining writes on its way, and where a
snapshot's skill quality is written. Torch-free, so that `sepoa experiment status` can tell
which of a grid's snapshots are still to pretrain and reports can read their quality."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from runvocab.config import RunConfig

QUALITY_FORMAT = "sepoa-skill-quality/1"
"""the format of a snapshot's skill-quality file (`trainer.skills.quality`)"""


def quality_path(snapshot: str) -> str:
    """Where the skill quality of the snapshot at `snapshot` is written."""
    return os.path.splitext(snapshot)[0] + ".quality.json"


ONLINE_SKILL_FIELDS = (
    "estimator_ensemble", "estimator_hidden_dim", "estimator_hidden_layers", "estimator_lr",
    "estimator_steps", "task_skill_samples", "task_skill_draw", "task_skill_update",
    "initial_rollouts", "reset_critic", "score_spread", "snapshot", "snapshot_dir",
    "snapshot_seed", "free_initial_rollouts", "estimator_data", "actor", "actor_std",
    "actor_clip", "estimator_refit",
)
"""skill fields only the online phase reads: they leave a pretrained snapshot unchanged"""


def snapshot_settings(cfg: RunConfig, seed: int) -> dict[str, Any]:
    """Every setting a pretraining with `seed` reads: two runs whose settings agree can share
    its snapshot."""
    skill = {k: v for k, v in dataclasses.asdict(cfg.skill).items()
             if k not in ONLINE_SKILL_FIELDS}
    return {"task": cfg.task, "seed": seed, "episode_length": cfg.episode_length,
            "replay_capacity": cfg.replay_capacity, "sac": dataclasses.asdict(cfg.sac),
            "skill": skill}


def default_snapshot_path(cfg: RunConfig, seed: int | None = None) -> str:
    """snapshot_dir/<task>-<backend>-<steps>-s<seed>-<hash>.pt (seed: cfg.seed): the one name
    `sepoa pretrain`, online runs and experiments use. The hash covers every setting
    pretraining reads (`snapshot_settings`), so a snapshot is never taken for another's."""
    seed = cfg.seed if seed is None else seed
    settings = json.dumps(snapshot_settings(cfg, seed), sort_keys=True, default=str)
    digest = hashlib.sha1(settings.encode()).hexdigest()[:10]
    name = f"{name_prefix(cfg)}{cfg.skill.pretrain_steps}-s{seed}-{digest}.pt"
    return os.path.join(cfg.skill.snapshot_dir, name)


def name_prefix(cfg: RunConfig) -> str:
    """`<task>-<backend>-`: how every snapshot name of the task and backend begins (their
    metrics files' too)."""
    return f"{cfg.task.replace(':', '-')}-{cfg.skill.backend}-"


def longer_pattern(cfg: RunConfig, seed: int) -> str:
    """A glob, in the snapshot folder, for the snapshots longer pretrainings of `seed` wrote on
    their way at `cfg`'s length (`intermediate_path`), whatever their other settings."""
    return f"{name_prefix(cfg)}*-s{seed}-*-at{cfg.skill.pretrain_steps}.pt"


SHARED_FOLDER = "snapshots"
"""the folder, in a worker's results or data folder, whose snapshots the runs there share"""


def shared_snapshot_dir(overrides: Mapping[str, Any], root: Path) -> dict[str, str]:
    """The override that puts a run's snapshots in `root`'s shared folder, unless the run's own
    overrides name a `skill.snapshot_dir`."""
    if "skill.snapshot_dir" in overrides:
        return {}
    return {"skill.snapshot_dir": str(root / SHARED_FOLDER)}


def snapshot_seed(cfg: RunConfig) -> int:
    """The pretraining seed of an online run's default snapshot: `skill.snapshot_seed`, or the
    run's own seed when that is -1."""
    return cfg.seed if cfg.skill.snapshot_seed < 0 else cfg.skill.snapshot_seed


def snapshot_path(cfg: RunConfig) -> str:
    """The snapshot an online run starts from: `skill.snapshot`, else the default name for its
    task, backend and pretraining length, pretrained with `snapshot_seed(cfg)`: runs of one
    seed (any teacher, eps or online setting) share it."""
    return cfg.skill.snapshot or default_snapshot_path(cfg, snapshot_seed(cfg))


def progress_path(path: str) -> str:
    """Where an unfinished pretraining of the snapshot `path` keeps its state."""
    return path + ".partial"


def intermediate_path(path: str, step: int) -> str:
    """The snapshot a pretraining bound for `path` writes on the way, at `step`."""
    root, ext = os.path.splitext(path)
    return f"{root}-at{step}{ext}"

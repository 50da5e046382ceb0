"""Presets as data, and a run's configuration built from them and written as JSON.

Presets are plain dictionaries of field overrides (dotted paths), applied in order: task family
(dmc / metaworld) → per-task feedback amounts → algorithm → algorithm and task → size preset
(paper / small / tiny) → explicit overrides.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from typing import Any

from runvocab.config.schema import RunConfig, unknown_field
from runvocab.names import ConfigError, task_family, unknown

FAMILY_PRESETS: dict[str, dict[str, Any]] = {
    "dmc": {"feedback.every": 20_000},
    "metaworld": {
        "sac.hidden_dim": 256,
        "sac.hidden_layers": 3,
        "sac.lr": 1e-4,
        "sac.batch_size": 512,
        "feedback.every": 5_000,
        "feedback.per_round": 100,
        "feedback.budget": 30_000,
        "reward.rime_k": 1 / 300,
    },
}

# The paper's feedback amounts (total / per round) per task.
TASK_PRESETS: dict[str, dict[str, Any]] = {
    "dmc:cheetah_run": {"feedback.budget": 1000, "feedback.per_round": 100},
    "dmc:walker_run": {"feedback.budget": 1000, "feedback.per_round": 100},
    "dmc:quadruped_walk": {"feedback.budget": 2000, "feedback.per_round": 200,
                           "skill.pretrain_steps": 1_000_000},
    "dmc:quadruped_run": {"feedback.budget": 2000, "feedback.per_round": 200,
                          "skill.pretrain_steps": 1_000_000},
    "metaworld:door-open": {"skill.pretrain_steps": 1_000_000},
}

PRESETS: dict[str, dict[str, Any]] = {
    # The paper's networks and schedule: GPU work (1 M steps, 1024-wide nets).
    "paper": {},
    # Learns on a 2-core CPU in about an hour per 100 k steps.
    "small": {
        "sac.hidden_dim": 256,
        "sac.hidden_layers": 2,
        "sac.batch_size": 256,
        "unsup_steps": 4000,
        "feedback.every": 5000,
        "replay_capacity": 200_000,
        "eval_every": 10_000,
        "eval_episodes": 5,
        "checkpoint_every": 20_000,
        "skill.hidden_dim": 256,
        "skill.pretrain_steps": 200_000,  # APS: ~15 min at ~230 steps/s on 2 CPU cores
        "skill.seed_steps": 2000,
        "skill.initial_rollouts": 10,  # 10 k steps: round 0 compares 45 skill pairs
    },
    # For tests and smoke runs: seconds, not minutes. Learns nothing useful.
    "tiny": {
        "sac.hidden_dim": 32,
        "sac.hidden_layers": 2,
        "sac.batch_size": 32,
        "reward.hidden_dim": 32,
        "reward.hidden_layers": 2,
        "reward.max_epochs": 5,
        "seed_steps": 200,
        "unsup_steps": 200,
        "feedback.segment_length": 20,
        "feedback.every": 400,
        "feedback.per_round": 10,
        "feedback.budget": 30,
        "feedback.candidate_factor": 5,
        "replay_capacity": 10_000,
        "eval_every": 0,
        "eval_episodes": 1,
        "checkpoint_every": 400,
        "episode_length": 200,
        "skill.hidden_dim": 32,
        "skill.pretrain_steps": 300,
        "skill.seed_steps": 100,
        "skill.initial_rollouts": 3,
        "reset_updates": 10,
        "reward.surf_crop_min": 15,  # segments of 20 here
        "reward.surf_crop_max": 18,
    },
}


# Per algorithm. SURF, RUNE and RIME are PEBBLE with one piece added; S-EPOA selects queries
# by its skill rule and, as in the paper, learns its reward with SURF.
SURF = {"reward.surf": True, "feedback.segment_length": 60}
ALGO_PRESETS: dict[str, dict[str, Any]] = {
    "surf": SURF,
    "rune": {"reward.rune": True},
    "rime": {"reward.rime": True},
    "sepoa": {"feedback.selection": "skill", "feedback.selection_mode": "per_query"} | SURF,
}
# RIME's own unsupervised pretraining length on cheetah (9000 elsewhere, PEBBLE's).
ALGO_TASK_PRESETS: dict[tuple[str, str], dict[str, Any]] = {
    ("rime", "dmc:cheetah_run"): {"unsup_steps": 2000},
}


def _replace_path(cfg: Any, path: str, value: Any, full: str = "") -> Any:
    head, _, rest = path.partition(".")
    if not any(f.name == head for f in dataclasses.fields(cfg)):
        raise unknown_field(full or path)
    if rest:
        inner = _replace_path(getattr(cfg, head), rest, value, full or path)
        return dataclasses.replace(cfg, **{head: inner})
    return dataclasses.replace(cfg, **{head: value})


def apply_overrides(cfg: RunConfig, overrides: dict[str, Any]) -> RunConfig:
    for path, value in overrides.items():
        cfg = _replace_path(cfg, path, value)
    return cfg


def preset_layers() -> dict[str, dict[str, dict[str, Any]]]:
    """Every preset layer, in the order `build_config` applies them (algorithm-and-task keys
    written "<algo> <task>")."""
    return {
        "family": FAMILY_PRESETS,
        "task": TASK_PRESETS,
        "algorithm": ALGO_PRESETS,
        "algorithm and task": {f"{a} {t}": v for (a, t), v in ALGO_TASK_PRESETS.items()},
        "size": PRESETS,
    }


def build_config(task: str, preset: str, overrides: dict[str, Any] | None = None) -> RunConfig:
    """The run config for `task` under `preset`: family, task, algorithm and size presets in
    that order (a size preset shrinks whatever came before), then explicit `overrides`
    (dotted paths)."""
    if preset not in PRESETS:
        raise ConfigError("preset", unknown("preset", preset, PRESETS))
    overrides = overrides or {}
    algo = overrides.get("algo", RunConfig.algo)
    cfg = RunConfig(task=task, preset=preset)
    cfg = apply_overrides(cfg, FAMILY_PRESETS.get(task_family(task), {}))
    cfg = apply_overrides(cfg, TASK_PRESETS.get(task, {}))
    cfg = apply_overrides(cfg, ALGO_PRESETS.get(algo, {}))
    cfg = apply_overrides(cfg, ALGO_TASK_PRESETS.get((algo, task), {}))
    cfg = apply_overrides(cfg, PRESETS[preset])
    return apply_overrides(cfg, overrides)


# A run's configuration as JSON: config.json in its folder, a queued run's stored copy.

WRITTEN_WHEN_SET = ("reward.init_from", "reward.true_reward", "sac.cuda_graph", "sac.tf32",
                    "skill.free_initial_rollouts", "skill.estimator_data", "skill.actor",
                    "skill.actor_std", "skill.actor_clip", "skill.estimator_refit")
"""fields added after runs were stored: a config's dict holds them only when they differ from
their default, so a stored config.json stays equal to the same run's config today (a results
folder's finished runs are recognised by that equality, `experiments.queue`)"""


def to_dict(cfg: RunConfig) -> dict[str, Any]:
    out = dataclasses.asdict(cfg)
    for path in WRITTEN_WHEN_SET:
        head, _, leaf = path.partition(".")
        section = getattr(cfg, head)
        default = {f.name: f.default for f in dataclasses.fields(section)}[leaf]
        if getattr(section, leaf) == default:
            del out[head][leaf]
    return out


def from_dict(data: dict[str, Any]) -> RunConfig:
    def build(cls: type, values: dict[str, Any]) -> Any:
        hints = typing.get_type_hints(cls)
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name not in values:
                continue
            v = values[f.name]
            if dataclasses.is_dataclass(hints[f.name]):
                v = build(hints[f.name], v)
            elif isinstance(v, list):
                v = tuple(v)
            kwargs[f.name] = v
        return cls(**kwargs)

    cfg: RunConfig = build(RunConfig, data)
    return cfg


def save_json(cfg: RunConfig, path: str) -> None:
    with open(path, "w") as f:
        json.dump(to_dict(cfg), f, indent=2, default=str)


def load_json(path: str) -> RunConfig:
    with open(path) as f:
        return from_dict(json.load(f))



"""One check of a whole run configuration, before any training: each refusal names the field,
what it holds and what is valid."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

from runvocab.config import RunConfig
from runvocab.names import (
    ALGOS,
    ESTIMATOR_DATA,
    SCORE_SPREADS,
    SELECTION_MODES,
    SELECTION_RULES,
    SIZE_PRESETS,
    SKILL_ACTORS,
    SKILL_BACKENDS,
    TASK_SKILL_DRAWS,
    TEACHER_KINDS,
    TIES,
    ConfigError,
    all_tasks,
    device_name_error,
    unknown,
    unknown_task,
)


def validate(cfg: RunConfig, pretraining: bool = False) -> None:
    """Raise a ConfigError for the first bad field of `cfg`. `pretraining`: `cfg` describes a
    skill pretraining run (`sepoa pretrain`), whose skill fields are checked whatever the algo."""
    _check_names(cfg)
    _check_sizes(cfg)
    _check_numbers(cfg)
    _check_feedback(cfg)
    _check_teacher(cfg)
    if cfg.reward.surf:
        _check_surf(cfg)
    if cfg.reward.rune:
        _check_rune(cfg)
    if cfg.reward.rime:
        _check_rime(cfg)
    if pretraining or cfg.algo == "sepoa":
        _check_skill(cfg, pretraining)
    if cfg.reward.true_reward:
        _check_true_reward(cfg)


def _positive(values: dict[str, float]) -> None:
    for name, value in values.items():
        if not value > 0:
            raise ConfigError(name, f"{name} must be positive, got {value}")


def _not_negative(values: dict[str, float]) -> None:
    for name, value in values.items():
        if value < 0:
            raise ConfigError(name, f"{name} cannot be negative, got {value}")


def _within(values: dict[str, tuple[float, float, float]]) -> None:
    for name, (value, low, high) in values.items():
        if not low <= value <= high:
            raise ConfigError(name, f"{name} must be between {low} and {high}, got {value}")


MAX_INT = 2**31 - 1
"""the largest whole number a run's field takes: what the queue database's INTEGER columns hold
(a run's step, its budget); a larger size is none a run could reach"""


def _leaves(obj: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _leaves(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, value


def _check_sizes(cfg: RunConfig) -> None:
    """Every whole number within +-MAX_INT, every other number finite (teacher.beta may be inf:
    a rational teacher)."""
    for path, value in _leaves(cfg):
        if isinstance(value, bool):
            continue
        if isinstance(value, int) and not -MAX_INT <= value <= MAX_INT:
            shown = str(value) if len(str(value)) <= 20 else f"{value:.3g}"
            raise ConfigError(path, f"{path} must be at most {MAX_INT} (2^31 - 1) in size, got "
                                    f"{shown}")
        if isinstance(value, float) and not math.isfinite(value) and path != "teacher.beta":
            raise ConfigError(path, f"{path} must be a finite number, got {value}")


def choice_fields() -> dict[str, tuple[str, ...]]:
    """The text fields that take one of a few values, by dotted path, and those values (the
    server's OpenAPI states them as enums)."""
    return {
        "task": all_tasks(), "algo": ALGOS, "preset": SIZE_PRESETS,
        "feedback.selection": SELECTION_RULES,
        "feedback.first_round_selection": SELECTION_RULES,
        "feedback.selection_mode": SELECTION_MODES,
        "feedback.compare_rule": ("", *SELECTION_RULES),
        "teacher.kind": TEACHER_KINDS, "teacher.tie": TIES, "skill.backend": SKILL_BACKENDS,
        "skill.task_skill_draw": TASK_SKILL_DRAWS, "skill.score_spread": SCORE_SPREADS,
        "skill.estimator_data": ESTIMATOR_DATA, "skill.actor": SKILL_ACTORS,
    }


def _value(cfg: RunConfig, path: str) -> Any:
    for name in path.split("."):
        cfg = getattr(cfg, name)
    return cfg


def _check_names(cfg: RunConfig) -> None:
    if cfg.task not in all_tasks():
        raise ConfigError("task", unknown_task(cfg.task))
    for name, valid in choice_fields().items():
        value = _value(cfg, name)
        if value not in valid:
            raise ConfigError(name, unknown(name, value, valid))
    problem = device_name_error(cfg.device)
    if problem:
        raise ConfigError("device", problem)


def _check_numbers(cfg: RunConfig) -> None:
    _positive({
        "steps": cfg.steps, "replay_capacity": cfg.replay_capacity,
        "update_every": cfg.update_every, "sac.batch_size": cfg.sac.batch_size,
        "sac.hidden_dim": cfg.sac.hidden_dim, "sac.hidden_layers": cfg.sac.hidden_layers,
        "sac.lr": cfg.sac.lr, "reward.batch_size": cfg.reward.batch_size,
        "reward.ensemble_size": cfg.reward.ensemble_size,
        "reward.hidden_dim": cfg.reward.hidden_dim, "reward.lr": cfg.reward.lr,
        "eval_episodes": cfg.eval_episodes,
    })
    _not_negative({
        "seed": cfg.seed, "seed_steps": cfg.seed_steps, "unsup_steps": cfg.unsup_steps,
        "reset_updates": cfg.reset_updates, "episode_length": cfg.episode_length,
        "eval_every": cfg.eval_every, "checkpoint_every": cfg.checkpoint_every,
        "threads": cfg.threads,
    })
    if cfg.skill.snapshot_seed < -1:
        raise ConfigError("skill.snapshot_seed", "skill.snapshot_seed is a seed (>= 0) or -1 "
                          f"for the run's own seed, got {cfg.skill.snapshot_seed}")
    if not 0 <= cfg.sac.gamma < 1:
        raise ConfigError("sac.gamma", f"sac.gamma is a discount in [0, 1), got {cfg.sac.gamma}")
    if not 0 < cfg.sac.tau <= 1:
        raise ConfigError("sac.tau", f"sac.tau is a Polyak rate in (0, 1], got {cfg.sac.tau}")


def _check_feedback(cfg: RunConfig) -> None:
    fb = cfg.feedback
    _positive({
        "feedback.segment_length": fb.segment_length, "feedback.every": fb.every,
        "feedback.per_round": fb.per_round, "feedback.candidate_factor": fb.candidate_factor,
        "feedback.pool_trajectories": fb.pool_trajectories,
    })
    _not_negative({"feedback.budget": fb.budget,
                   "skill.initial_rollouts": cfg.skill.initial_rollouts})
    _within({"feedback.labels_per_query": (fb.labels_per_query, 1, 10),
             "feedback.gold_rate": (fb.gold_rate, 0.0, 0.5),
             "feedback.gold_min_accuracy": (fb.gold_min_accuracy, 0.0, 1.0),
             "feedback.gold_min_answers": (fb.gold_min_answers, 1, 10_000),
             "feedback.practice_pairs": (fb.practice_pairs, 0, 20)})
    if fb.pool_trajectories < 2:
        raise ConfigError("feedback.pool_trajectories",
                          "feedback.pool_trajectories must be at least 2 (a query pairs two)")
    for name in ("selection", "first_round_selection", "compare_rule"):
        if getattr(fb, name) == "skill" and cfg.algo != "sepoa":
            raise ConfigError(f"feedback.{name}",
                              f"feedback.{name} skill needs skills: use algo sepoa")
    if fb.first_round_selection == "skill":
        raise ConfigError("feedback.first_round_selection",
                          "feedback.first_round_selection cannot be skill: before the first "
                          "label there is no return estimate to select by")
    if cfg.algo == "sepoa" and cfg.skill.initial_rollouts > fb.pool_trajectories:
        raise ConfigError("skill.initial_rollouts",
                          f"skill.initial_rollouts {cfg.skill.initial_rollouts} exceeds "
                          f"feedback.pool_trajectories {fb.pool_trajectories}: round 0 could "
                          "never see them all")
    if cfg.episode_length and cfg.episode_length < fb.segment_length:
        raise ConfigError("episode_length",
                          f"episode_length {cfg.episode_length} is shorter than a segment "
                          f"({fb.segment_length} steps)")


def _check_teacher(cfg: RunConfig) -> None:
    t = cfg.teacher
    if not 0 <= t.eps < 1:
        raise ConfigError("teacher.eps", f"teacher.eps is an error rate in [0, 1), got {t.eps}")
    if t.recent_trajectories < 1:
        raise ConfigError("teacher.recent_trajectories",
                          f"teacher.recent_trajectories must be at least 1, got "
                          f"{t.recent_trajectories}")
    if math.isnan(t.beta) or t.beta < 0:
        raise ConfigError("teacher.beta",
                          f"teacher.beta must be >= 0 (inf = rational), got {t.beta}")
    for name, value in {"teacher.gamma": t.gamma, "teacher.eps_mistake": t.eps_mistake}.items():
        if not 0 <= value <= 1:
            raise ConfigError(name, f"{name} must be in [0, 1], got {value}")
    _not_negative({"teacher.eps_skip": t.eps_skip, "teacher.eps_equal": t.eps_equal})


def _check_surf(cfg: RunConfig) -> None:
    r, segment = cfg.reward, cfg.feedback.segment_length
    if not 0 < r.surf_crop_min <= r.surf_crop_max:
        raise ConfigError("reward.surf_crop_min",
                          f"reward.surf_crop_min ({r.surf_crop_min}) must be positive and at "
                          f"most reward.surf_crop_max ({r.surf_crop_max})")
    if r.surf_crop_max > segment:
        raise ConfigError("reward.surf_crop_max",
                          f"reward.surf_crop_max ({r.surf_crop_max}) exceeds "
                          f"feedback.segment_length ({segment}); SURF crops segments of 60 "
                          "steps in the paper")
    if not 0.5 < r.surf_threshold < 1:
        raise ConfigError("reward.surf_threshold",
                          f"reward.surf_threshold is a confidence in (0.5, 1), got "
                          f"{r.surf_threshold}")
    _not_negative({"reward.surf_unlabelled_ratio": r.surf_unlabelled_ratio,
                   "reward.surf_weight": r.surf_weight})


def _check_rune(cfg: RunConfig) -> None:
    r = cfg.reward
    _not_negative({"reward.rune_beta0": r.rune_beta0})
    if not 0 <= r.rune_decay < 1:
        raise ConfigError("reward.rune_decay",
                          f"reward.rune_decay is a rate in [0, 1), got {r.rune_decay}")


def _check_rime(cfg: RunConfig) -> None:
    r = cfg.reward
    if not 0 < r.rime_beta_min <= r.rime_beta_max:
        raise ConfigError("reward.rime_beta_min",
                          f"reward.rime_beta_min ({r.rime_beta_min}) must be positive and at "
                          f"most reward.rime_beta_max ({r.rime_beta_max})")
    _positive({"reward.rime_k": r.rime_k, "reward.rime_tau_upper": r.rime_tau_upper})
    _not_negative({"reward.rime_alpha": r.rime_alpha,
                   "reward.rime_warm_start_updates": r.rime_warm_start_updates})


def _check_skill(cfg: RunConfig, pretraining: bool) -> None:
    s = cfg.skill
    # 0 = the backend's own skill size and skill period.
    _not_negative({"skill.skill_dim": s.skill_dim,
                   "skill.update_skill_every": s.update_skill_every,
                   "skill.pretrain_steps": s.pretrain_steps, "skill.seed_steps": s.seed_steps})
    _positive({
        "skill.update_every": s.update_every, "skill.hidden_dim": s.hidden_dim,
        "skill.hidden_layers": s.hidden_layers, "skill.knn_k": s.knn_k, "skill.lr": s.lr,
        "skill.temperature": s.temperature, "skill.estimator_ensemble": s.estimator_ensemble,
        "skill.estimator_hidden_dim": s.estimator_hidden_dim,
        "skill.estimator_lr": s.estimator_lr, "skill.task_skill_samples": s.task_skill_samples,
        "skill.actor_std": s.actor_std, "skill.actor_clip": s.actor_clip,
    })
    _not_negative({"skill.estimator_steps": s.estimator_steps})
    if cfg.algo == "sepoa" and not s.estimator_refit and cfg.feedback.selection != "skill":
        raise ConfigError("skill.estimator_refit",
                          f"skill.estimator_refit false fits R_theta only as a round selects "
                          f"by the skill rule; with feedback.selection "
                          f"{cfg.feedback.selection!r} it would never be fitted: keep it true, "
                          f"or select by 'skill'")
    if (pretraining or s.pretrain_steps > 0) and s.knn_k > cfg.sac.batch_size:
        raise ConfigError("skill.knn_k",
                          f"skill.knn_k ({s.knn_k}) exceeds the batch (sac.batch_size "
                          f"{cfg.sac.batch_size}) its neighbours come from")


def _check_true_reward(cfg: RunConfig) -> None:
    """The diagnostic replaces r_hat for an agent that would learn one: a preference run whose
    reward adds nothing that needs a reward model."""
    if cfg.algo == "sac":
        raise ConfigError("reward.true_reward", "reward.true_reward applies to preference "
                          "runs (pebble, surf, sepoa); algo sac trains on the true reward "
                          "already")
    for name in ("rune", "rime"):
        if getattr(cfg.reward, name):
            raise ConfigError("reward.true_reward", f"reward.true_reward cannot go with "
                              f"reward.{name}, whose reward needs the learned model")
    if not cfg.skill.estimator_refit:
        raise ConfigError("reward.true_reward", "reward.true_reward fits R_theta on true "
                          "returns once a round, with no reward model to fit it before or "
                          "after: it cannot go with skill.estimator_refit false")

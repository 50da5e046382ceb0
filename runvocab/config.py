"""Typed, frozen run configuration, presets as data, and a command-line reader for both.

A run is described by one `RunConfig`. Presets are plain dictionaries of field overrides,
applied in order: task family (dmc / metaworld) → per-task feedback amounts → preset
(paper / small / tiny) → explicit command-line flags.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import typing
from dataclasses import dataclass, field
from typing import Any

from runvocab.names import ConfigError, did_you_mean, task_family, unknown


@dataclass(frozen=True)
class SACConfig:
    """Soft actor-critic; defaults are the paper's DMControl values."""

    hidden_dim: int = 1024
    """width of every hidden layer of actor and critic"""
    hidden_layers: int = 2
    """number of hidden layers of actor and critic"""
    lr: float = 5e-4
    """Adam learning rate of actor, critic and temperature"""
    batch_size: int = 1024
    """transitions per update"""
    init_temperature: float = 0.2
    """initial entropy temperature alpha"""
    gamma: float = 0.99
    """discount"""
    tau: float = 0.01
    """Polyak rate of the target critic"""
    target_update_every: int = 2
    """critic target update period, in updates"""
    actor_update_every: int = 1
    """actor and temperature update period, in updates"""
    log_std_min: float = -5.0
    """lower bound of the actor's log standard deviation"""
    log_std_max: float = 2.0
    """upper bound of the actor's log standard deviation"""
    betas: tuple[float, float] = (0.9, 0.999)
    """Adam betas"""


@dataclass(frozen=True)
class RewardConfig:
    """The preference reward model: an ensemble of MLPs on (s, a) with a tanh output."""

    ensemble_size: int = 3
    """members of the ensemble"""
    hidden_dim: int = 256
    """width of each hidden layer"""
    hidden_layers: int = 3
    """hidden layers per member"""
    lr: float = 3e-4
    """Adam learning rate"""
    batch_size: int = 128
    """labelled pairs per gradient step"""
    max_epochs: int = 50
    """upper bound on passes over all labels per round"""
    stop_accuracy: float = 0.98
    """stop a round's training once the mean training accuracy reaches this"""
    surf: bool = False
    """SURF: temporal crops of labelled pairs and confident pseudo-labels of unlabelled ones"""
    surf_crop_min: int = 45
    """SURF: shortest crop, in steps (segments of 60 in the paper)"""
    surf_crop_max: int = 55
    """SURF: longest crop, in steps"""
    surf_unlabelled_ratio: int = 4
    """SURF: unlabelled pairs per labelled pair in each batch"""
    surf_threshold: float = 0.999
    """SURF: a pseudo-label needs P above this (or below 1 - this)"""
    surf_weight: float = 1.0
    """SURF: weight of the pseudo-labelled pairs' loss"""
    rune: bool = False
    """RUNE: the agent's reward gets a bonus of beta_t times the ensemble's std of r_hat"""
    rune_beta0: float = 0.05
    """RUNE: beta_0, the bonus weight when the agent starts training on r_hat"""
    rune_decay: float = 0.001
    """RUNE: rho; beta_t = beta_0 (1 - rho)^t, t = environment steps since the first round"""
    rime: bool = False
    """RIME: train only on labels the model trusts (KL bound), flip confidently contradicted
    ones, and warm-start the model on the intrinsic reward before the first round"""
    rime_alpha: float = 0.5
    """RIME: alpha of the lower bound -ln(rho) + alpha rho"""
    rime_beta_max: float = 3.0
    """RIME: initial weight of the KL spread in the bound"""
    rime_beta_min: float = 1.0
    """RIME: final weight of the KL spread in the bound"""
    rime_k: float = 1 / 30
    """RIME: beta falls linearly by k per training epoch (1/30 DMC, 1/300 Metaworld)"""
    rime_tau_upper: float = 6.907755278982137
    """RIME: 3 ln 10; cap of the spread term and the KL beyond which a label is flipped"""
    rime_warm_start_updates: int = 5
    """RIME: reward-model regression steps on the intrinsic reward per pretraining update"""


@dataclass(frozen=True)
class TeacherConfig:
    """Who answers queries. `noisy` is the paper's teacher (eps = 0 is the ideal one);
    `bpref` has B-Pref's knobs."""

    kind: str = "noisy"
    """noisy | bpref"""
    eps: float = 0.0
    """noisy: random label when |R(tau0) - R(tau1)| < eps * R_avg"""
    beta: float = math.inf
    """bpref: Bradley-Terry rationality (inf = always prefers the larger return)"""
    gamma: float = 1.0
    """bpref: myopic discount of earlier steps within a segment"""
    eps_mistake: float = 0.0
    """bpref: probability of flipping an answer"""
    eps_skip: float = 0.0
    """bpref: skip when both segment returns are below eps_skip * margin"""
    eps_equal: float = 0.0
    """bpref: answer 'equal' when the segment returns differ by less than eps_equal * margin"""
    recent_trajectories: int = 10
    """how many recent trajectories give R_avg (and B-Pref's margin)"""
    tie: str = "equal"
    """answer when the two segments' true sums are exactly equal: equal (label 0.5; the paper's
    labels are one-hot) | random | first (B-Pref's code)"""


@dataclass(frozen=True)
class FeedbackConfig:
    """The preference-learning loop (PEBBLE's schedule)."""

    segment_length: int = 50
    """steps per segment"""
    every: int = 20_000
    """environment steps between feedback rounds"""
    per_round: int = 100
    """queries per round"""
    budget: int = 1000
    """total queries over the run, the first round included"""
    selection: str = "disagreement"
    """uniform | disagreement | entropy | skill (S-EPOA's; algo sepoa)"""
    candidate_factor: int = 10
    """candidates per query: N of per_query, or per_round * candidate_factor for top_k"""
    selection_mode: str = "top_k"
    """per_query: each query is the best of its own candidate_factor random pairs (the paper's
    Algorithm 2) | top_k: the round's best per_round of one draw (PEBBLE's and the authors'
    code; with a small pool it piles a round onto one trajectory)"""
    compare_rule: str = ""
    """diagnostic: also select each round by this rule on the same pool and reward model (a
    random stream of its own; nothing is asked) and log how many of its picks the run's teacher
    could tell apart (rounds.csv compare_distinguishable_ratio); empty = off"""
    pool_trajectories: int = 100
    """candidates come from the last N finished trajectories"""
    first_round_selection: str = "uniform"
    """rule for the first round, when no label exists yet and the ensemble is untrained"""
    wait_for_labels: bool = True
    """people teaching: pause training until a round is answered (false: keep training on the
    current reward and use what arrived when the next round is due)"""
    labels_per_query: int = 1
    """people teaching: distinct labellers who answer each query (1-10); the reward model trains
    on their majority (`runvocab.answers.aggregate`)"""
    gold_rate: float = 0.0
    """people teaching: the share of each labeller's answers given to gold pairs, known-answer
    pairs that measure them and are never trained on (0-0.5; `labelqueue.gold`)"""
    gold_min_accuracy: float = 0.0
    """pause a labeller on the run whose accuracy on gold pairs falls below this (0: never)"""
    gold_min_answers: int = 10
    """gold answers a labeller gives before `gold_min_accuracy` can pause them"""


@dataclass(frozen=True)
class SkillConfig:
    """Unsupervised skill discovery (S-EPOA's pretraining); defaults are the paper's APS."""

    backend: str = "aps"
    """aps | diayn | cic"""
    skill_dim: int = 0
    """skill vector size; 0 = the backend's own (APS 10, DIAYN 16, CIC 64)"""
    update_skill_every: int = 0
    """pretraining: steps between fresh skills; 0 = the backend's own (APS 5, DIAYN/CIC 50)"""
    pretrain_steps: int = 500_000
    """environment steps of pretraining (the paper: 500 k, 1 M for quadruped and door-open)"""
    seed_steps: int = 4000
    """pretraining: uniformly random actions at the start (URLB's seed frames)"""
    update_every: int = 2
    """pretraining: environment steps per SAC and skill-net update (URLB: 2)"""
    lr: float = 1e-4
    """pretraining: Adam learning rate of SAC and the skill nets (fine-tuning uses sac.lr)"""
    hidden_dim: int = 1024
    """width of the skill nets' hidden layers (APS features, DIAYN discriminator, CIC nets)"""
    hidden_layers: int = 2
    """hidden layers of each skill net"""
    beta: float = 5.0
    """APS: weight of the particle-entropy term of the intrinsic reward"""
    knn_k: int = 12
    """APS and CIC: neighbours of the kNN particle entropy, over the batch"""
    knn_clip: float = 1e-4
    """APS and CIC: subtracted from the mean-normalised kNN distances, floored at 0 (URLB)"""
    temperature: float = 0.5
    """CIC: temperature of the contrastive (InfoNCE) logits"""
    estimator_ensemble: int = 3
    """online: members of R_theta(z), the trajectory-return estimator"""
    estimator_hidden_dim: int = 256
    """online: width of R_theta's hidden layers"""
    estimator_hidden_layers: int = 3
    """online: hidden layers of R_theta"""
    estimator_lr: float = 3e-4
    """online: Adam learning rate of R_theta"""
    estimator_steps: int = 200
    """online: full-batch steps refitting R_theta before each round"""
    task_skill_samples: int = 50
    """online: N_z, fresh random skills z_task is chosen from"""
    task_skill_draw: str = "refit"
    """online: when z_task is drawn anew: refit (when a round has refitted R_theta, held in
    between) | episode (also at every episode start, as the authors' code; behind on the
    return in specs/small/sepoa-choices.toml)"""
    task_skill_update: bool = True
    """online: every other update trains on its batch with z_task in place of every stored
    skill (valid off-policy: r_hat does not depend on z), taking turns with the update on the
    stored skills: one SAC update per update step in all, as every algorithm"""
    initial_rollouts: int = 20
    """online: episodes, each with its own random skill, before the first round (the authors'
    reward_start_rollouts)"""
    reset_critic: bool = True
    """online: at the first round, reset the pretrained critic and its target (the actor is
    kept), then run `reset_updates` updates on the learned reward (kept, the agent waited
    until 20-25 k steps to move in specs/small/sepoa-choices.toml)"""
    score_spread: str = "var"
    """online: spread of P in the selection score: var (the paper) | std (the authors' code)"""
    snapshot_dir: str = "snapshots"
    """where `sepoa pretrain` writes <task>-<backend>-<steps>-s<seed>.pt by default"""
    snapshot: str = ""
    """online S-EPOA: the snapshot to start from; empty = the default name in snapshot_dir"""
    snapshot_seed: int = -1
    """online S-EPOA: the pretraining seed of the default snapshot; -1 = the run's own seed (a
    snapshot per seed, so seeds sample pretraining too); a fixed seed shares one snapshot"""


@dataclass(frozen=True)
class RunConfig:
    """One training run: environment, algorithm, schedule, teacher, logging."""

    task: str = "dmc:cheetah_run"
    """dmc:<domain>_<task> or metaworld:<name>"""
    algo: str = "pebble"
    """pebble | surf | rune | rime | sepoa (preference learning) | sac (the oracle on the
    ground-truth reward)"""
    preset: str = "paper"
    """paper | small | tiny"""
    seed: int = 0
    """seeds the environment, networks, sampling and teacher"""
    steps: int = 1_000_000
    """environment steps"""
    episode_length: int = 0
    """steps per episode; 0 = the task's own (1000 DMC, 500 Metaworld)"""
    seed_steps: int = 1000
    """uniformly random actions at the start"""
    unsup_steps: int = 9000
    """unsupervised state-entropy pretraining steps after the seed steps (pebble only)"""
    entropy_k: int = 5
    """k of the kNN state-entropy reward during pretraining"""
    update_every: int = 1
    """environment steps per SAC update"""
    reset_updates: int = 100
    """SAC updates on the relabelled buffer right after a critic reset (PEBBLE's reset_update)"""
    replay_capacity: int = 1_000_000
    """transitions kept in the replay buffer"""
    eval_every: int = 10_000
    """environment steps between evaluations (0 = never)"""
    eval_episodes: int = 10
    """episodes per evaluation"""
    checkpoint_every: int = 50_000
    """environment steps between checkpoints (also one at every feedback round)"""
    device: str = "auto"
    """auto | cpu | cuda"""
    threads: int = 0
    """torch CPU threads; 0 = torch's default"""
    run_dir: str = ""
    """where metrics, labels and checkpoints go; empty = runs/<task>-<algo>-s<seed>"""
    sac: SACConfig = field(default_factory=SACConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    feedback: FeedbackConfig = field(default_factory=FeedbackConfig)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    skill: SkillConfig = field(default_factory=SkillConfig)


# ---------------------------------------------------------------------------------------------
# Presets: plain data. Keys are dotted field paths.

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


def _unknown_field(path: str) -> ConfigError:
    paths = [p for p, _, _ in _leaf_fields(RunConfig)]
    return ConfigError(path, f"unknown config field {path!r}{did_you_mean(path, paths)}; "
                             "`sepoa train --help` lists every field")


def _replace_path(cfg: Any, path: str, value: Any, full: str = "") -> Any:
    head, _, rest = path.partition(".")
    if not any(f.name == head for f in dataclasses.fields(cfg)):
        raise _unknown_field(full or path)
    if rest:
        inner = _replace_path(getattr(cfg, head), rest, value, full or path)
        return dataclasses.replace(cfg, **{head: inner})
    return dataclasses.replace(cfg, **{head: value})


def apply_overrides(cfg: RunConfig, overrides: dict[str, Any]) -> RunConfig:
    for path, value in overrides.items():
        cfg = _replace_path(cfg, path, value)
    return cfg


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


def typed_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """Overrides from JSON (a run's stored config) checked against the fields' types: ints
    stay ints (a whole float is taken), floats take ints, bools and strings must be exact."""
    types = {path: t for path, t, _ in _leaf_fields(RunConfig)}
    out = {}
    for path, value in values.items():
        if path not in types:
            raise _unknown_field(path)
        t, bad = types[path], False
        if t is bool or t is str:
            bad = not isinstance(value, t)
        elif t is int:
            bad = isinstance(value, bool) or not (
                isinstance(value, int) or (isinstance(value, float) and value.is_integer()))
            value = value if bad else int(value)
        elif t is float:
            bad = isinstance(value, bool) or not isinstance(value, int | float)
            value = value if bad else float(value)
        if bad:
            raise ConfigError(path, f"config field {path!r} takes {t.__name__}, got {value!r}")
        out[path] = value
    return out


def to_dict(cfg: RunConfig) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


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


# ---------------------------------------------------------------------------------------------
# Command line: every leaf field becomes a flag (`--sac.lr 1e-4`); the common ones also have
# short aliases (`--eps`, `--selection`, `--budget`, ...).

ALIASES = {
    "eps": "teacher.eps",
    "selection": "feedback.selection",
    "budget": "feedback.budget",
    "per-round": "feedback.per_round",
    "feedback-every": "feedback.every",
    "skills": "skill.backend",
}


@functools.cache  # reading the docs parses source: once per class, not per call
def _leaf_fields(cls: type, prefix: str = "") -> tuple[tuple[str, type, str], ...]:
    hints = typing.get_type_hints(cls)
    out: list[tuple[str, type, str]] = []
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            out += _leaf_fields(t, f"{prefix}{f.name}.")
        else:
            out.append((prefix + f.name, t, _field_doc(cls, f.name)))
    return tuple(out)


def _field_doc(cls: type, name: str) -> str:
    import inspect

    lines = inspect.getsource(cls).splitlines()
    for i, line in enumerate(lines):
        if line.strip().startswith(f"{name}:") and i + 1 < len(lines):
            doc = lines[i + 1].strip()
            if doc.startswith('"""'):
                return doc.strip('"')
    return ""


def _parse_value(t: Any, text: str) -> Any:
    if t is bool:
        return text.lower() in ("1", "true", "yes", "on")
    if t is int:
        return int(float(text)) if "e" in text.lower() else int(text)
    if t is float:
        return float(text)
    if typing.get_origin(t) is tuple:
        return tuple(float(x) for x in text.split(","))
    return text


def add_config_arguments(parser: argparse.ArgumentParser,
                         exclude: tuple[str, ...] = ()) -> None:
    """A flag per leaf field but task, preset and `exclude` (which a command defines itself)."""
    for path, t, doc in _leaf_fields(RunConfig):
        if path in ("task", "preset", *exclude):
            continue
        names = [f"--{path}"] + [f"--{a}" for a, p in ALIASES.items() if p == path]
        if "_" in path:
            names.append(f"--{path.replace('_', '-')}")
        parser.add_argument(
            *names, dest=path, default=None, metavar=t.__name__.upper() if hasattr(t, "__name__")
            else "VALUE", help=doc,
            type=lambda s, t=t: _parse_value(t, s),  # type: ignore[misc]
        )


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return {
        path: getattr(args, path)
        for path, _, _ in _leaf_fields(RunConfig)
        if path not in ("task", "preset") and getattr(args, path, None) is not None
    }

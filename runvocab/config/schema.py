"""What a run is configured by: typed, frozen dataclasses with a one-line docstring per field,
and the one parser of a field's value, from the command line (text) or from JSON.

A run is described by one `RunConfig`; a field is named by its dotted path (`sac.lr`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from runvocab.names import ConfigError, did_you_mean


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
    cuda_graph: bool = False
    """on a CUDA device, replay the update from CUDA graphs (trainer/graphed_update.py): the
    same update without a kernel launch per operation; ignored on the CPU"""
    tf32: bool = False
    """on a CUDA device, float32 matrix products in TF32 (10-bit mantissa), for the whole
    process: at the paper's sizes the graphed update is bound by arithmetic, which TF32 runs
    on the tensor cores; ignored on the CPU"""


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
    bf16: bool = False
    """train the members' forward passes in bfloat16 autocast (weights and optimiser stay in
    float32): a round 2.1-2.8x faster on a CPU with AVX-512 BF16 (benchmarks/README.md);
    slower where the CPU lacks it"""
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
    true_reward: bool = False
    """diagnostic: the agent trains on the environment's true reward where it would train on
    r_hat; rounds keep their schedule and budget but ask nothing and train no reward model, and
    S-EPOA's R_theta is refitted on true returns (the agent side alone:
    specs/small/sepoa-true-reward.toml)"""
    init_from: str = ""
    """a reward model file (`sepoa reward fit --out`) whose ensemble weights the run's reward
    model starts from instead of random ones; empty: random (its observation and action sizes
    and its ensemble's size and shape must be the run's)"""


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
    """total answers over the run, the first round included: a query costs the answers it gets
    (`labels_per_query` people's, or the scripted teacher's one); gold pairs cost nothing"""
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
    practice_pairs: int = 0
    """people teaching: a practice round of this many gold pairs before a labeller's first
    answer on the run, each explained once answered; never trained on, not counted in gold
    accuracy (0-20; `labelqueue.practice`). Each round then has at least this many gold pairs"""


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
    """online: full-batch steps of each fit of R_theta (the authors' code: 50)"""
    estimator_refit: bool = True
    """online: R_theta is fitted again after each round's reward training, so z_task follows
    the new reward model at once. false (the authors' code): fitted only as a round selects
    (on the reward model before its labels), none at the first round, so z_task until the
    second round is the argmax of the unfitted R_theta"""
    task_skill_samples: int = 50
    """online: N_z, fresh random skills z_task is chosen from"""
    task_skill_draw: str = "episode"
    """online: when z_task is drawn anew: episode (at every episode start, the paper's
    Algorithm 1 and the authors' code) | refit (only when a round has refitted R_theta, held in
    between; the fair grid's setting)"""
    task_skill_update: bool = True
    """online: every other update trains on its batch with z_task in place of every stored
    skill (valid off-policy: r_hat does not depend on z), taking turns with the update on the
    stored skills: one SAC update per update step in all, as every algorithm"""
    initial_rollouts: int = 20
    """online: episodes, each with its own random skill, before the first round (the authors'
    reward_start_rollouts)"""
    free_initial_rollouts: bool = False
    """online: the initial rollouts are played on the evaluation env before step 0 and are not
    counted as environment steps; the first round follows at once, then `reset_updates`
    updates, and the agent learns from step 0 (the authors' code). false: they are the run's
    first steps, and it learns from the first round on"""
    estimator_data: str = "pool"
    """online: what R_theta is fitted on: pool (the query pool's trajectories, some 16-20
    distinct skills at the small preset) | replay (every complete episode in the replay
    buffer, the authors' code)"""
    actor: str = "sac"
    """online: sac (a learned sigma, alpha from the snapshot) | ddpg (URLB's actor as the
    authors fine-tune it: the pretrained mean with a fixed sigma `actor_std`, noise clipped at
    `actor_clip` in the updates, actions bounded with a straight-through gradient, and alpha
    tuned as SAC's from 1, their initial value: it only shifts the critic's target)"""
    actor_std: float = 0.2
    """online, actor ddpg: the fixed standard deviation of the exploration noise"""
    actor_clip: float = 0.3
    """online, actor ddpg: the bound of the noise in the actor's and the target's actions"""
    reset_critic: bool = True
    """online: at the first round, reset the pretrained critic and its target (the actor is
    kept), then run `reset_updates` updates on the learned reward (kept, the agent waited
    until 20-25 k steps to move in specs/small/sepoa-choices.toml)"""
    score_spread: str = "var"
    """online: spread of P in the selection score: var (the paper) | std (the authors' code)"""
    snapshot_dir: str = "snapshots"
    """where `sepoa pretrain` writes <task>-<backend>-<steps>-s<seed>-<hash>.pt by default (the
    hash covers every setting pretraining reads)"""
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
    """unsupervised state-entropy pretraining steps after the seed steps (PEBBLE, SURF, RUNE
    and RIME; sac and sepoa have none)"""
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
    """environment steps between checkpoints (also one as each feedback round opens and closes)"""
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


class Leaf(NamedTuple):
    """A field that holds a value (not a section), by its dotted path."""

    path: str
    kind: Any
    """its type: bool, int, float, str or a tuple of those"""
    section: type
    """the dataclass that declares it"""
    name: str


@functools.cache
def leaf_fields() -> tuple[Leaf, ...]:
    """Every value field of a `RunConfig`, in declaration order."""
    return tuple(_leaves(RunConfig, ""))


def _leaves(cls: type, prefix: str) -> list[Leaf]:
    hints = typing.get_type_hints(cls)
    out: list[Leaf] = []
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if isinstance(t, type) and dataclasses.is_dataclass(t):
            out += _leaves(t, f"{prefix}{f.name}.")
        else:
            out.append(Leaf(prefix + f.name, t, cls, f.name))
    return out


@functools.cache
def _kinds() -> dict[str, Any]:
    return {leaf.path: leaf.kind for leaf in leaf_fields()}


def unknown_field(path: str) -> ConfigError:
    paths = [leaf.path for leaf in leaf_fields()]
    return ConfigError(path, f"unknown config field {path!r}{did_you_mean(path, paths)}; "
                             "`sepoa train --help` lists every field")


BOOL_WORDS = {"true": True, "yes": True, "on": True, "1": True,
              "false": False, "no": False, "off": False, "0": False}
"""the spellings a bool takes, as text on the command line or in JSON (any case)"""
BOOL_SPELLINGS = "true/false, yes/no, on/off or 1/0"


def parse_value(path: str, value: Any) -> Any:
    """`value` for the field at `path`, from the command line (text) or JSON (text, or a value of
    the field's type): a bool is one of `BOOL_WORDS` (or JSON's true/false, 0 or 1); an int
    takes a whole number, also written as a float (`1e6`, `2.0`); a float any number; a str
    only text; a tuple its items, comma-separated as text or a JSON list. Anything else is a
    ConfigError that names the field and what it takes, never a silent default."""
    if path not in _kinds():
        raise unknown_field(path)
    kind = _kinds()[path]
    try:
        return _convert(kind, value)
    except (TypeError, ValueError, OverflowError):
        spellings = f"; use {BOOL_SPELLINGS}" if kind is bool else ""
        raise ConfigError(path, f"config field {path!r} takes {_kind_name(kind)}, got "
                                f"{value!r}{spellings}") from None


def _convert(kind: Any, value: Any) -> Any:
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in BOOL_WORDS:
            return BOOL_WORDS[value.strip().lower()]
        if type(value) is int and value in (0, 1):
            return bool(value)
    elif kind is int:
        if isinstance(value, str):
            value = _number(value)
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif kind is float:
        if isinstance(value, str):
            return float(value)
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif kind is str:
        if isinstance(value, str):
            return value
    elif typing.get_origin(kind) is tuple:
        items = value.split(",") if isinstance(value, str) else value
        kinds = typing.get_args(kind)
        if isinstance(items, list | tuple) and len(items) == len(kinds):
            return tuple(_convert(k, item) for k, item in zip(kinds, items, strict=True))
    else:
        raise NotImplementedError(f"no parser for fields of type {kind}")
    raise ValueError(value)


def _number(text: str) -> int | float:
    try:
        return int(text)
    except ValueError:
        return float(text)


def _kind_name(kind: Any) -> str:
    if typing.get_origin(kind) is tuple:
        names = [k.__name__ for k in typing.get_args(kind)]
        return f"{len(names)} values ({', '.join(names)}), comma-separated"
    return str(kind.__name__)


def typed_overrides(values: dict[str, Any]) -> dict[str, Any]:
    """Overrides (dotted paths) from JSON, TOML or the command line, each value parsed by
    `parse_value`."""
    return {path: parse_value(path, value) for path, value in values.items()}

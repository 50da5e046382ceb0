"""Offline reward fitting: the project's reward ensemble trained on a dataset export's labels.

    sepoa reward fit datasets/sepoa/dmc-cheetah_run/run-3-v0 --out cheetah-reward.pt

The labelled pairs are the export's answered queries (`queries.parquet`) whose aggregate is
first, second or equal, gold pairs aside (never trained on, as in a run). A seeded share of them
(`holdout`) is held out; the ensemble (the run's own `reward` configuration from `sepoa.json`)
trains on the rest as a run of this version trains its own: after each feedback round's pairs
join, on every pair so far, with the run's loss and early stopping (`RewardModel.train_round`),
SURF's crops and pseudo-labels included when the run used them (or once on all of them:
`schedule`).
Reported: the held-out accuracy (the share of held-out first/second pairs whose summed r_hat
orders the two segments as their aggregate does), the training accuracy, the accuracy on random
segment pairs ordered by their true returns, and the Pearson correlation of r_hat with the true
reward over every step of the dataset's episodes. The saved file (`save_reward_model`) is what
a new run starts from with `reward.init_from`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
import torch

from rundata.dataset import DatasetError, LabelledDataset
from runvocab.answers import Answer
from runvocab.config import RewardConfig
from trainer.reward_file import save_ensemble
from trainer.reward_model import LabelledPairs, RewardModel
from trainer.surf import PairSampler
from trainer.teachers import choice_target


@dataclass(frozen=True)
class Pairs:
    seg0: np.ndarray
    """(n, H, obs_dim + action_dim) float32"""
    seg1: np.ndarray
    targets: np.ndarray
    """(n,) P[second preferred]: 0, 1 or 0.5"""
    query_ids: np.ndarray
    rounds: np.ndarray
    """(n,) the feedback round that asked each pair"""


def _segment(dataset: LabelledDataset, episode: int, start: int, length: int) -> np.ndarray:
    e = dataset.episodes[episode]
    return np.concatenate([e.observations[start:start + length],
                           e.actions[start:start + length]], axis=1)


def labelled_pairs(dataset: LabelledDataset) -> Pairs:
    """The dataset's trainable pairs: answered, not gold, aggregate first/second/equal."""
    seg0, seg1, targets, ids, rounds = [], [], [], [], []
    for q in dataset.queries:
        if q.get("gold") or q["aggregate"] is None:
            continue
        target = choice_target(Answer(q["aggregate"]))
        if target is None:
            continue
        h = q["segment_length"]
        seg0.append(_segment(dataset, q["first_episode"], q["first_start"], h))
        seg1.append(_segment(dataset, q["second_episode"], q["second_start"], h))
        targets.append(target)
        ids.append(q["query_id"])
        rounds.append(q["round"])
    if not targets:
        raise DatasetError(f"{dataset.path}: no query has a first, second or equal answer to "
                           "train on")
    if len({s.shape for s in seg0 + seg1}) > 1:
        raise DatasetError(f"{dataset.path}: the labelled segments differ in length; a fit "
                           "needs segments of one length")
    return Pairs(np.stack(seg0), np.stack(seg1), np.asarray(targets, np.float32),
                 np.asarray(ids), np.asarray(rounds))


def split(pairs: Pairs, holdout: float, seed: int) -> tuple[Pairs, Pairs]:
    """A seeded (train, held-out) split; `holdout` is the held-out share."""
    n = len(pairs.targets)
    order = np.random.default_rng(seed).permutation(n)
    k = int(round(n * holdout))
    if holdout > 0 and (k < 1 or k >= n):
        raise DatasetError(f"{n} labelled pairs cannot be split {1 - holdout:.0%} / "
                           f"{holdout:.0%}: give more labels or another --holdout")
    held, train = order[:k], order[k:]

    def take(idx: np.ndarray) -> Pairs:
        return Pairs(pairs.seg0[idx], pairs.seg1[idx], pairs.targets[idx],
                     pairs.query_ids[idx], pairs.rounds[idx])

    return take(train), take(held)


@torch.no_grad()
def pair_accuracy(model: RewardModel, pairs: Pairs) -> float:
    """The share of decisive pairs (target 0 or 1) whose summed r_hat (the ensemble mean) puts
    the preferred segment first; nan without decisive pairs."""
    decisive = pairs.targets != 0.5
    if not decisive.any():
        return float("nan")
    returns = [segment_returns(model, s[decisive]) for s in (pairs.seg0, pairs.seg1)]
    second = pairs.targets[decisive] > 0.5
    return float(np.mean((returns[1] > returns[0]) == second))


@torch.no_grad()
def segment_returns(model: RewardModel, segments: np.ndarray) -> np.ndarray:
    """(n, H, D) segments -> (n,) summed ensemble-mean r_hat."""
    n, h, d = segments.shape
    flat = torch.as_tensor(segments.reshape(n * h, d), device=model.device)
    return model.member_rewards(flat).mean(0).reshape(n, h).sum(1).cpu().numpy()


@torch.no_grad()
def reward_correlation(model: RewardModel, dataset: LabelledDataset) -> float:
    """Pearson correlation of r_hat with the true reward over every step of the episodes."""
    obs = np.concatenate([e.observations[:-1] for e in dataset.episodes])
    actions = np.concatenate([e.actions for e in dataset.episodes])
    true = np.concatenate([e.rewards for e in dataset.episodes]).astype(np.float64)
    r_hat = model.reward(torch.as_tensor(obs, device=model.device),
                         torch.as_tensor(actions, device=model.device)).cpu().numpy()
    if true.std() == 0 or r_hat.std() == 0:
        return float("nan")
    return float(np.corrcoef(r_hat.astype(np.float64), true)[0, 1])


def reward_config(dataset: LabelledDataset, epochs: int | None) -> RewardConfig:
    """The run's reward configuration (the defaults when the export has none), with at most
    `epochs` passes per training (default: the run's `max_epochs`)."""
    stored = (dataset.info.get("config") or {}).get("reward") or {}
    known = {f.name for f in dataclasses.fields(RewardConfig)}
    cfg = RewardConfig(**{k: v for k, v in stored.items() if k in known})
    return dataclasses.replace(cfg, init_from="",
                               max_epochs=epochs if epochs is not None else cfg.max_epochs)


@dataclass(frozen=True)
class FitResult:
    model: RewardModel
    metrics: dict[str, float]
    train: Pairs
    heldout: Pairs


SCHEDULES = ("rounds", "once")
"""rounds: train after each feedback round's pairs join, on every pair so far, as the run did;
once: one training on all the pairs"""


def fit(dataset: LabelledDataset, *, holdout: float = 0.2, seed: int = 0,
        epochs: int | None = None, device: str = "cpu", schedule: str = "rounds") -> FitResult:
    """Train a reward ensemble on the dataset's labelled pairs (module docstring)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule {schedule!r}: give one of {', '.join(SCHEDULES)}")
    pairs = labelled_pairs(dataset)
    train, held = split(pairs, holdout, seed)
    cfg = reward_config(dataset, epochs)
    torch.manual_seed(seed)
    obs_dim, action_dim = int(dataset.info["obs_dim"]), int(dataset.info["action_dim"])
    model = RewardModel(obs_dim, action_dim, cfg, torch.device(device), seed)
    unlabelled = _unlabelled_pairs(dataset, pairs.seg0.shape[1], seed) if cfg.surf else None
    start = time.perf_counter()
    labelled = LabelledPairs()
    steps = sorted(set(train.rounds.tolist())) if schedule == "rounds" else [None]
    epochs_run = 0
    for round_ in steps:
        for s0, s1, y, r in zip(train.seg0, train.seg1, train.targets, train.rounds,
                                strict=True):
            if round_ is None or r == round_:
                labelled.add(s0, s1, float(y))
        epochs_run += int(model.train_round(labelled, unlabelled)["reward_epochs"])
    truth = true_order_pairs(dataset, TRUE_ORDER_PAIRS, pairs.seg0.shape[1], seed)
    metrics: dict[str, float] = {  # the counts as ints, so that they print as counts
        "pairs": len(pairs.targets), "train_pairs": len(train.targets),
        "heldout_pairs": len(held.targets),
        "heldout_decisive": int((held.targets != 0.5).sum()),
        "heldout_accuracy": pair_accuracy(model, held),
        "train_accuracy": pair_accuracy(model, train),
        "reward_corr": reward_correlation(model, dataset),
        "true_order_accuracy": pair_accuracy(model, truth),
        "trainings": len(steps), "epochs": epochs_run,
        "seconds": time.perf_counter() - start,
    }
    return FitResult(model, metrics, train, held)


TRUE_ORDER_PAIRS = 1000
"""random segment pairs ordered by their true returns, on which fits are compared too"""


def _long_enough(dataset: LabelledDataset, length: int) -> list[int]:
    """The episodes that hold a segment of `length` steps."""
    return [i for i, e in enumerate(dataset.episodes) if e.length >= length]


def true_order_pairs(dataset: LabelledDataset, n: int, length: int, seed: int) -> Pairs:
    """`n` random pairs of segments of `length` steps from two different episodes at least
    that long (the same one when there is only one), each targeted by which has the larger true
    return (exact ties left out): pairs no model trained on, judged by the task itself. No
    pairs when no episode is that long or every pair ties (`pair_accuracy` is then nan)."""
    rng = np.random.default_rng([seed, 0x7A0E])
    episodes, long = dataset.episodes, _long_enough(dataset, length)
    seg0, seg1, targets = [], [], []
    for _ in range(n if long else 0):
        a = int(rng.integers(len(long)))
        b = a if len(long) == 1 else int((a + rng.integers(1, len(long))) % len(long))
        a, b = long[a], long[b]
        sa, sb = (int(rng.integers(episodes[i].length - length + 1)) for i in (a, b))
        ra = episodes[a].rewards[sa:sa + length].sum(dtype=np.float64)
        rb = episodes[b].rewards[sb:sb + length].sum(dtype=np.float64)
        if ra == rb:
            continue
        seg0.append(_segment(dataset, a, sa, length))
        seg1.append(_segment(dataset, b, sb, length))
        targets.append(1.0 if rb > ra else 0.0)
    dim = episodes[0].observations.shape[1] + episodes[0].actions.shape[1] if episodes else 0
    none = np.zeros((0, length, dim), np.float32)
    return Pairs(np.stack(seg0) if seg0 else none, np.stack(seg1) if seg1 else none,
                 np.asarray(targets, np.float32), np.arange(len(targets)),
                 np.zeros(len(targets), np.int64))


def run_reward_model(checkpoint: str, dataset: LabelledDataset) -> RewardModel:
    """The exported run's own reward model as its checkpoint (`checkpoint.pt` in its run
    folder) holds it; ValueError when the file holds none of the dataset's shape."""
    from trainer.checkpoint import load_checkpoint

    try:
        state = load_checkpoint(checkpoint)
    except FileNotFoundError:
        raise ValueError(f"--compare: no file {checkpoint}") from None
    except Exception as err:  # noqa: BLE001 - torch raises several kinds for a bad file
        raise ValueError(f"--compare: {checkpoint} is not a run's checkpoint ({err})") from None
    if "feedback" not in state:
        raise ValueError(f"--compare: {checkpoint} holds no reward model (a SAC run)")
    cfg = reward_config(dataset, None)
    model = RewardModel(int(dataset.info["obs_dim"]), int(dataset.info["action_dim"]), cfg,
                        torch.device("cpu"), 0)
    try:
        model.ensemble.load_state_dict(state["feedback"]["model"]["ensemble"])
    except RuntimeError:
        raise ValueError(f"--compare: {checkpoint}'s reward model has another shape than the "
                         "dataset's run") from None
    return model


def compare(run_model: RewardModel, result: FitResult, dataset: LabelledDataset,
            seed: int = 0) -> dict[str, float]:
    """The run's own model on the fit's held-out pairs (which it trained on, as on every label
    of the run), on the same true-order pairs, and its r_hat correlation."""
    truth = true_order_pairs(dataset, TRUE_ORDER_PAIRS, result.heldout.seg0.shape[1]
                             if len(result.heldout.targets) else result.train.seg0.shape[1],
                             seed)
    return {"run_heldout_accuracy": pair_accuracy(run_model, result.heldout),
            "run_true_order_accuracy": pair_accuracy(run_model, truth),
            "run_reward_corr": reward_correlation(run_model, dataset)}


def _unlabelled_pairs(dataset: LabelledDataset, length: int, seed: int) -> PairSampler:
    """SURF's unlabelled pairs: random segments of the episodes at least `length` steps
    long."""
    rng = np.random.default_rng([seed, 0x5E6])
    episodes, long = dataset.episodes, np.asarray(_long_enough(dataset, length))
    if not len(long):
        raise DatasetError(f"{dataset.path}: no episode holds a segment of {length} steps")

    def sample(n: int) -> tuple[np.ndarray, np.ndarray]:
        sides = []
        for _ in range(2):
            which = long[rng.integers(len(long), size=n)]
            segs = [
                _segment(dataset, int(i),
                         int(rng.integers(episodes[i].length - length + 1)), length)
                for i in which]
            sides.append(np.stack(segs))
        return sides[0], sides[1]

    return sample


def save_reward_model(path: str, result: FitResult, dataset: LabelledDataset) -> None:
    """The fitted ensemble as `reward.init_from` reads it (trainer/reward_file.py)."""
    save_ensemble(path, result.model.ensemble, result.model.cfg, task=dataset.task,
                  obs_dim=int(dataset.info["obs_dim"]), action_dim=int(dataset.info["action_dim"]),
                  dataset=str(dataset.info.get("dataset_id")), fit=result.metrics)

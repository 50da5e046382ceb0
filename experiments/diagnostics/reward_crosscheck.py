"""Is a low score the reward model's fault or the policy's? Every run's reward model scores
every run's policy, on the same episodes.

For each run folder given (its checkpoint is read from a copy; the run itself is not touched),
its policy plays `--episodes` deterministic episodes as the loop evaluates it (S-EPOA with its
z_task), every policy on fresh environments of the same seeds, so that all face the same
starts. Then each run's reward model (the SAC oracle has none) is judged on all of them:

- which policy it scores highest (the mean of r_hat summed over each episode), where it ranks
  its own run's policy among them (1: first) against where the true return ranks it, and the
  rank correlation of its scores with the policies' true returns;
- how well it orders what every policy did, one set for all models: the rank correlation of
  summed r_hat with the true return over all episodes; the share of random segment pairs
  from two different episodes it orders as their true returns do (the pairs `sepoa reward
  fit` scores, the same pairs for every model); the Pearson correlation of r_hat with the
  true reward over every step (a run's own `reward_corr` is taken over its own replay buffer,
  which another arm's agent filled differently);
- the same pair accuracy on its own policy's episodes only.

How to read it: a reward model that ranks its own policy below another run's policy that
truly returns more knew of better behaviour that its policy did not reach (the policy fell
short of its own reward). One that ranks its own policy above policies that truly return more
scores the better behaviour too low: where the other models rank the same policy near its true
rank, that is the model's own error, which its policy found (it trained on this model's reward)
or which the model makes off the states its labels came from; the cross-check does not tell
these two apart.

    .venv/bin/python -m experiments.diagnostics.reward_crosscheck RUN_DIR [RUN_DIR ...] \\
        [--episodes 5] [--pairs 2000] [--segment 50] [--csv scores.csv]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo's import

from experiments.diagnostics.run_copy import resume_copy  # noqa: E402
from experiments.diagnostics.skill_choice import spearman  # noqa: E402
from rundata.dataset import DatasetEpisode, LabelledDataset  # noqa: E402
from runvocab.config import RewardConfig  # noqa: E402
from trainer.envs import make_env  # noqa: E402
from trainer.feedback import PreferenceFeedback  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402
from trainer.reward_fit import pair_accuracy, reward_correlation, true_order_pairs  # noqa: E402
from trainer.reward_model import LabelledPairs, RewardModel  # noqa: E402


@dataclass(frozen=True)
class Played:
    """One run's policy's episodes, and its reward model."""

    label: str
    algo: str
    step: int
    episodes: list[DatasetEpisode]
    model: RewardModel | None
    """None for the SAC oracle, which learns from the true reward"""
    refitted: RewardModel | None = None
    """with --refit: a fresh model on the run's own labels, which its policy never trained on"""
    labels: LabelledPairs | None = None
    reward_cfg: RewardConfig | None = None

    @property
    def variant(self) -> str:
        """the label's first part: the run's arm in a grid"""
        return self.label.split("/")[0]

    @property
    def true_return(self) -> float:
        return float(np.mean([e.rewards.sum(dtype=np.float64) for e in self.episodes]))


@dataclass(frozen=True)
class Judgement:
    """One reward model's view of every policy (`played` in order)."""

    learned_returns: np.ndarray
    """(policies,) mean summed r_hat over each policy's episodes"""
    own: int
    """the index of the model's own run"""
    own_true_rank: int
    """1 + the policies that truly return more than the model's own run's"""
    policy_rank_corr: float
    """over the policies: mean summed r_hat against true return"""
    episode_rank_corr: float
    pair_accuracy: float
    own_pair_accuracy: float
    step_corr: float
    refitted_rank: int | None = None
    """where a fresh model on the same labels (--refit) ranks the run's own policy"""

    def rank_of(self, policy: int) -> int:
        return rank(self.learned_returns, policy)

    @property
    def own_rank(self) -> int:
        return self.rank_of(self.own)

    @property
    def favourite(self) -> int:
        return int(np.argmax(self.learned_returns))


def rank(scores: np.ndarray, i: int) -> int:
    """1 + the entries of `scores` above entry `i` (a tie does not rank above it)"""
    return 1 + int(np.sum(scores > scores[i]))


def play(run: TrainingRun, episodes: int, seed: int) -> list[DatasetEpisode]:
    """Deterministic episodes of the run's policy as the loop's evaluation acts, on a fresh
    environment seeded `seed`."""
    env = make_env(run.cfg.task, seed, run.cfg.episode_length or None)
    rng = np.random.default_rng(seed)
    played = []
    for _ in range(episodes):
        obs, done = env.reset(), False
        seen, actions, rewards = [obs], [], []
        while not done:
            action = run.policy.act(obs, run.policy.eval_meta(run.meta), rng, True)
            result = env.step(action)
            obs, done = result.obs, result.done
            seen.append(obs)
            actions.append(action)
            rewards.append(result.reward)
        observations = np.asarray(seen, np.float32)
        played.append(DatasetEpisode(observations=observations,
                                     actions=np.asarray(actions, np.float32),
                                     rewards=np.asarray(rewards, np.float32),
                                     states=np.zeros((len(seen), 0)), context=0))
    return played


def fresh_model(pairs: LabelledPairs, cfg: RewardConfig, like: DatasetEpisode,
                seed: int) -> RewardModel:
    """A reward model initialised from `seed` and trained once on `pairs` with `cfg`: SURF's
    crops where `cfg` has them, not its unlabelled pairs, which a run draws from its pool as each
    round closes. `like`: an episode of the task, for the model's input sizes."""
    with torch.random.fork_rng():  # the initial weights come from torch's global stream
        torch.manual_seed(seed)
        model = RewardModel(like.observations.shape[1], like.actions.shape[1],
                            dataclasses.replace(cfg, init_from=""), torch.device("cpu"), seed)
    model.train_round(pairs)
    return model


def load(run_dir: str, episodes: int, seed: int, threads: int) -> Played:
    with tempfile.TemporaryDirectory() as into:
        run = resume_copy(run_dir, into, threads)
        feedback = run.feedback if isinstance(run.feedback, PreferenceFeedback) else None
        label = "/".join(Path(os.path.abspath(run_dir)).parts[-3:])
        return Played(label, run.cfg.algo, run.step, play(run, episodes, seed),
                      feedback.model if feedback else None,
                      labels=feedback.pairs if feedback else None, reward_cfg=run.cfg.reward)


def refit(p: Played, seed: int) -> Played:
    """`p` with a fresh model on its own labels (none for the oracle)."""
    if p.labels is None or p.reward_cfg is None:
        return p
    return dataclasses.replace(p, refitted=fresh_model(p.labels, p.reward_cfg, p.episodes[0],
                                                       seed))


def pooled_model(played: list[Played], variants: set[str], seed: int) -> tuple[RewardModel,
                                                                             list[Played]]:
    """A fresh model trained once on the labels of every run of `variants` (all runs with
    labels when empty) together, with the first such run's reward configuration; and those
    runs."""
    sources = [p for p in played if p.labels is not None and (not variants or
                                                               p.variant in variants)]
    if not sources:
        raise SystemExit(f"--pooled-from {','.join(sorted(variants))}: no such run has labels "
                         f"(variants: {', '.join(sorted({p.variant for p in played}))})")
    pairs = LabelledPairs()
    for p in sources:
        assert p.labels is not None
        for s0, s1, y in zip(p.labels.seg0, p.labels.seg1, p.labels.targets, strict=True):
            pairs.add(s0, s1, y)
    assert sources[0].reward_cfg is not None
    return fresh_model(pairs, sources[0].reward_cfg, sources[0].episodes[0], seed), sources


def as_dataset(episodes: list[DatasetEpisode]) -> LabelledDataset:
    """Episodes in the form `sepoa reward fit`'s measures read."""
    return LabelledDataset(path=Path("crosscheck"), info={}, episodes=episodes, queries=[])


@torch.no_grad()
def learned_return(model: RewardModel, episode: DatasetEpisode) -> float:
    r_hat = model.reward(torch.as_tensor(episode.observations[:-1], device=model.device),
                         torch.as_tensor(episode.actions, device=model.device))
    return float(r_hat.sum(dtype=torch.float64))


def policy_scores(model: RewardModel, played: list[Played]) -> np.ndarray:
    """(policies,) the model's mean summed r_hat over each policy's episodes"""
    return np.array([np.mean([learned_return(model, e) for e in p.episodes]) for p in played])


def judge(played: list[Played], pairs: int, segment: int, seed: int) -> dict[int, Judgement]:
    """Each reward model's judgement of every policy, keyed by its run's index in `played`."""
    everything = as_dataset([e for p in played for e in p.episodes])
    shared_pairs = true_order_pairs(everything, pairs, segment, seed)
    true_returns = np.array([e.rewards.sum(dtype=np.float64) for e in everything.episodes])
    policy_returns = np.array([p.true_return for p in played])
    judged = {}
    for i, p in enumerate(played):
        if p.model is None:
            continue
        per_policy = [[learned_return(p.model, e) for e in q.episodes] for q in played]
        own_pairs = true_order_pairs(as_dataset(p.episodes), pairs, segment, seed)
        learned = np.array([np.mean(r) for r in per_policy])
        refitted_rank = None
        if p.refitted is not None:
            refitted_rank = rank(policy_scores(p.refitted, played), i)
        judged[i] = Judgement(
            learned_returns=learned, own=i, refitted_rank=refitted_rank,
            own_true_rank=rank(policy_returns, i),
            policy_rank_corr=spearman(learned, policy_returns),
            episode_rank_corr=spearman(np.concatenate(per_policy), true_returns),
            pair_accuracy=pair_accuracy(p.model, shared_pairs),
            own_pair_accuracy=pair_accuracy(p.model, own_pairs),
            step_corr=reward_correlation(p.model, everything))
    return judged


def print_by_variant(played: list[Played], judged: dict[int, Judgement]) -> None:
    """Each variant's (the label's first part: an arm of a grid) means over its models."""
    variants: dict[str, list[Judgement]] = {}
    for i, j in judged.items():
        variants.setdefault(played[i].variant, []).append(j)
    print("\nvariant  models  ranks own first  | means: rank corr over policies  | over every "
          "episode: rank corr  pair acc  step corr  | pair acc on its own policy")
    for name, js in variants.items():
        def mean(field: str, js: list[Judgement] = js) -> float:
            return float(np.mean([getattr(j, field) for j in js]))
        print(f"{name}  {len(js)}  {sum(j.own_rank == 1 for j in js)}  | "
              f"{mean('policy_rank_corr'):+.2f}  | {mean('episode_rank_corr'):+.2f}  "
              f"{mean('pair_accuracy'):.3f}  {mean('step_corr'):+.2f}  | "
              f"{mean('own_pair_accuracy'):.3f}")


def print_pooled(played: list[Played], judged: dict[int, Judgement], model: RewardModel,
                 sources: list[Played], pairs: int, segment: int, seed: int) -> None:
    """Where a model of several runs' labels ranks every policy, against the truth and each
    policy's own model."""
    everything = as_dataset([e for p in played for e in p.episodes])
    scores = policy_scores(model, played)
    truth = np.array([p.true_return for p in played])
    accuracy = pair_accuracy(model, true_order_pairs(everything, pairs, segment, seed))
    print(f"\na fresh model on the labels of {len(sources)} runs "
          f"({', '.join(sorted({p.variant for p in sources}))}; "
          f"{sum(len(p.labels or ()) for p in sources)} labels): rank corr over policies "
          f"{spearman(scores, truth):+.2f}, pair acc {accuracy:.3f}")
    print("policy  | rank by truth  by the pooled model  by its own model  | its labels pooled")
    for i in np.argsort(-truth, kind="stable"):
        own = f"{judged[i].own_rank:2d}" if i in judged else " -"
        print(f"{played[i].label}  | {rank(truth, i):2d}  {rank(scores, i):2d}  {own}  | "
              f"{'yes' if any(p is played[i] for p in sources) else 'no'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                        help="run folders holding a checkpoint, of one task")
    parser.add_argument("--episodes", type=int, default=5,
                        help="deterministic episodes per policy")
    parser.add_argument("--pairs", type=int, default=2000,
                        help="random segment pairs each model orders")
    parser.add_argument("--segment", type=int, default=50, help="steps per segment")
    parser.add_argument("--seed", type=int, default=0,
                        help="the environments' and the pairs' seed")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--refit", type=int, metavar="SEED",
                        help="also train a fresh reward model on each run's labels, initialised "
                             "from SEED, and say where it ranks the run's own policy (up to the "
                             "run's max_epochs passes over every label: minutes a run on a CPU)")
    parser.add_argument("--pooled", type=int, metavar="SEED",
                        help="also train one fresh reward model on the labels of several runs "
                             "together, initialised from SEED, and rank every policy by it")
    parser.add_argument("--pooled-from", default="", metavar="VARIANTS",
                        help="the variants (a run label's first part, comma-separated) whose "
                             "runs' labels --pooled trains on; default: every run with labels")
    parser.add_argument("--csv", help="also write every model's score of every policy here")
    args = parser.parse_args()
    if args.episodes < 2 or args.pairs < 1 or args.segment < 1:
        parser.error("--episodes must be at least 2 (pairs come from two different episodes), "
                     "--pairs and --segment at least 1")
    torch.set_num_threads(args.threads)

    played = [load(d, args.episodes, args.seed, args.threads) for d in args.run_dirs]
    tasks = {p.episodes[0].observations.shape[1] for p in played}
    if len(tasks) > 1:
        raise SystemExit("the runs' observations differ in size: give runs of one task")
    if min(e.length for p in played for e in p.episodes) < args.segment:
        raise SystemExit(f"an episode is shorter than --segment {args.segment}")
    if args.refit is not None:  # minutes a run: only once the runs are known to fit together
        played = [refit(p, args.refit) for p in played]
    pooled = None  # trained before the judging, so that a --pooled-from typo costs no wait
    if args.pooled is not None:
        variants = {v for v in args.pooled_from.split(",") if v}
        pooled = pooled_model(played, variants, args.pooled)
    judged = judge(played, args.pairs, args.segment, args.seed)

    by_truth = np.argsort([-p.true_return for p in played], kind="stable")
    print(f"{len(played)} policies, {args.episodes} episodes each; true return, best first:")
    for rank, i in enumerate(by_truth, 1):
        p = played[i]
        print(f"  {rank:2d}. {p.label}  ({p.algo}, step {p.step})  {p.true_return:.1f}")
    refitted = " (by a fresh model on its labels)" if args.refit is not None else ""
    print(f"\nreward model of  | its own policy's rank of {len(played)}: by its r_hat{refitted}, "
          "by the other models' (median), by truth  | favourite (its true return)  | rank corr "
          "over policies  | over every episode: rank corr  pair acc  step corr  | pair acc on "
          "its own policy")
    for i, j in judged.items():
        fav = played[j.favourite]
        others = [k.rank_of(i) for m, k in judged.items() if m != i]
        by_others = f"{np.median(others):4.1f}" if others else "   -"
        again = f" ({j.refitted_rank:2d})" if j.refitted_rank is not None else ""
        print(f"{played[i].label}  | {j.own_rank:2d}{again}  {by_others}  {j.own_true_rank:2d}  | "
              f"{fav.label} "
              f"({fav.true_return:.1f})  | {j.policy_rank_corr:+.2f}  | "
              f"{j.episode_rank_corr:+.2f}  {j.pair_accuracy:.3f}  {j.step_corr:+.2f}  | "
              f"{j.own_pair_accuracy:.3f}", flush=True)
    print_by_variant(played, judged)
    if pooled is not None:
        print_pooled(played, judged, *pooled, args.pairs, args.segment, args.seed)
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["model", "policy", "policy_algo", "learned_return", "true_return"])
            for i, j in judged.items():
                for k, q in enumerate(played):
                    writer.writerow([played[i].label, q.label, q.algo,
                                     f"{j.learned_returns[k]:.6g}", f"{q.true_return:.6g}"])


if __name__ == "__main__":
    main()

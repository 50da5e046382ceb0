"""Does R_theta pick a skill the policy does well with? z_task against random skills, measured on
an S-EPOA run's checkpoint.

S-EPOA acts, and is evaluated, with z_task: the best of N_z random skills under R_theta, which is
regressed on skills and their trajectories' summed r_hat, the pool's or the replay buffer's
(`skill.estimator_data`, trainer/return_estimator.py).
For each run folder given (its checkpoint is read from a copy; the run itself is not touched):

- `--skills` random skills from the run's skill prior (a random stream of this script's own),
  each scored by R_theta and measured: the true return of `--episodes` deterministic episodes of
  pi(a|s,z) on a fresh environment seeded `--seed`; the run's z_task is measured the same way,
  first, so that its figure is what the loop's own evaluation gives on such an environment;
- R_theta's rank correlation with the measured returns over the random skills (Spearman) and the
  return of R_theta's pick among them; the same for r_hat summed over each skill's measured
  episodes (whether the reward model tells the skills apart where R_theta does not);
- the best, median and worst random skill's return (the best also measured again on fresh
  episodes, as the best of many measurements is biased upwards);
- where z_task's return stands among the random skills' (the share it beats);
- what R_theta was fitted on: the pool's trajectories and how many distinct skills they hold.

A rank correlation near 0 says R_theta's choice is as good as a random skill's; a wide spread of
returns across skills says the choice matters.

    .venv/bin/python -m experiments.diagnostics.skill_choice RUN_DIR [RUN_DIR ...] [--skills 50] \\
        [--episodes 1] [--threads 1] [--csv skills.csv]
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile
from dataclasses import dataclass

import numpy as np
import torch

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo's import

from experiments.diagnostics.run_copy import resume_copy  # noqa: E402
from trainer.envs import Env, make_env  # noqa: E402
from trainer.feedback import PreferenceFeedback  # noqa: E402
from trainer.loop import TrainingRun  # noqa: E402
from trainer.policies import EpisodeMeta, SkillPolicy  # noqa: E402


@dataclass(frozen=True)
class SkillChoice:
    step: int
    predicted: np.ndarray
    """R_theta of each random skill"""
    learned_returns: np.ndarray
    """each random skill's summed r_hat over its measured episodes"""
    returns: np.ndarray
    """the measured return of each random skill"""
    task_return: float
    """the measured return of the run's z_task"""
    best_again: float
    """the best random skill's return on fresh episodes"""
    pool_trajectories: int
    pool_skills: int
    """distinct skills among the pool's trajectories: the points R_theta was fitted on"""

    @property
    def rank_correlation(self) -> float:
        return spearman(self.predicted, self.returns)

    @property
    def learned_rank_correlation(self) -> float:
        """how well r_hat summed over a skill's own episodes ranks the skills"""
        return spearman(self.learned_returns, self.returns)

    @property
    def pick_return(self) -> float:
        """the return of R_theta's choice among the random skills"""
        return float(self.returns[int(np.argmax(self.predicted))])

    @property
    def learned_pick_return(self) -> float:
        """the return of the random skill whose episodes r_hat scores highest"""
        return float(self.returns[int(np.argmax(self.learned_returns))])

    @property
    def task_beats(self) -> float:
        """the share of random skills whose return z_task's exceeds (ties count half)"""
        return float(np.mean((self.task_return > self.returns)
                             + 0.5 * (self.task_return == self.returns)))


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Rank correlation (average ranks for ties); NaN when either side is constant."""
    rx, ry = _ranks(x), _ranks(y)
    if rx.std() == 0 or ry.std() == 0:
        return float("nan")
    return float(np.corrcoef(rx, ry)[0, 1])


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x), dtype=float)
    for value in np.unique(x):  # ties share their average rank
        tied = x == value
        ranks[tied] = ranks[tied].mean()
    return ranks


def resume_skill_run(run_dir: str, into: str, threads: int, snapshot: str = "") -> TrainingRun:
    """An S-EPOA run resumed from a copy of its files (run_copy.py), once it has a z_task."""
    run = resume_copy(run_dir, into, threads, snapshot)
    if run.cfg.algo != "sepoa":
        raise SystemExit(f"{run_dir}: a {run.cfg.algo} run; only S-EPOA acts with skills")
    if not isinstance(run.policy, SkillPolicy) or run.policy.task_skill is None:
        raise SystemExit(f"{run_dir}: no z_task yet (before the first round)")
    return run


def skill_returns(run: TrainingRun, env: Env, skill: np.ndarray, episodes: int,
                  rng: np.random.Generator) -> tuple[float, float]:
    """Mean true return, and mean summed r_hat, of deterministic episodes of pi(a|s, skill)."""
    assert isinstance(run.feedback, PreferenceFeedback)
    meta, true_returns, learned_returns = EpisodeMeta(skill), [], []
    for _ in range(episodes):
        obs, total, done = env.reset(), 0.0, False
        seen, actions = [], []
        while not done:
            action = run.policy.act(obs, meta, rng, True)
            seen.append(obs)
            actions.append(action)
            result = env.step(action)
            obs, total, done = result.obs, total + result.reward, result.done
        true_returns.append(total)
        with torch.no_grad():
            learned = run.feedback.model.reward(
                torch.as_tensor(np.stack(seen), dtype=torch.float32),
                torch.as_tensor(np.stack(actions), dtype=torch.float32))
        learned_returns.append(float(learned.sum(dtype=torch.float64)))
    return float(np.mean(true_returns)), float(np.mean(learned_returns))


def measure(run_dir: str, skills: int, episodes: int, threads: int, seed: int,
            snapshot: str = "") -> SkillChoice:
    with tempfile.TemporaryDirectory() as into:
        run = resume_skill_run(run_dir, into, threads, snapshot)
        policy = run.policy
        assert isinstance(policy, SkillPolicy) and policy.task_skill is not None
        rng = np.random.default_rng(seed)
        env = make_env(run.cfg.task, seed, run.cfg.episode_length or None)
        # z_task first: on a fresh env of the run's evaluation seed it plays the run's evaluation.
        task_return, _ = skill_returns(run, env, policy.task_skill, episodes, rng)
        candidates = policy.skills.sample_skills(rng, skills)
        predicted = policy.estimator.predict(candidates).numpy()
        returns, learned = np.array([skill_returns(run, env, z, episodes, rng)
                                     for z in candidates]).T
        # The best of many measured returns is biased upwards: measured again on fresh episodes.
        best_again, _ = skill_returns(run, env, candidates[int(np.argmax(returns))], episodes,
                                      rng)
        pool = [t.skill.tobytes() for t in run.pool.trajectories if t.skill is not None]
        return SkillChoice(run.step, predicted, learned, returns, task_return, best_again,
                           len(pool), len(set(pool)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR",
                        help="S-EPOA run folders holding a checkpoint")
    parser.add_argument("--skills", type=int, default=50,
                        help="random skills measured (the runs' N_z is 50)")
    parser.add_argument("--episodes", type=int, default=1,
                        help="deterministic episodes per skill")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="the random skills' and envs' seed")
    parser.add_argument("--snapshot", default="",
                        help="the runs' skill snapshot, where it cannot be found by its name")
    parser.add_argument("--csv", help="also write every skill's prediction and return here")
    args = parser.parse_args()
    if args.skills < 2 or args.episodes < 1:
        parser.error("--skills must be at least 2 and --episodes at least 1")

    rows = []
    print("run  step  pool (distinct skills)  z_task  beats  | R_theta: rank corr  pick  "
          "| r_hat of the episodes: rank corr  pick  | best (again)  median  worst")
    for run_dir in args.run_dirs:
        c = measure(run_dir, args.skills, args.episodes, args.threads, args.seed, args.snapshot)
        print(f"{run_dir}  {c.step}  {c.pool_trajectories} ({c.pool_skills})  "
              f"{c.task_return:.1f}  {c.task_beats:.2f}  | {c.rank_correlation:+.2f}  "
              f"{c.pick_return:.1f}  | {c.learned_rank_correlation:+.2f}  "
              f"{c.learned_pick_return:.1f}  | {c.returns.max():.1f} ({c.best_again:.1f})  "
              f"{np.median(c.returns):.1f}  {c.returns.min():.1f}", flush=True)
        rows += [{"run": run_dir, "step": c.step, "skill": i, "predicted": float(p),
                  "learned_return": float(q), "return": float(r)}
                 for i, (p, q, r) in enumerate(zip(c.predicted, c.learned_returns, c.returns,
                                                   strict=True))]
        rows.append({"run": run_dir, "step": c.step, "skill": "z_task", "predicted": "",
                     "learned_return": "", "return": c.task_return})
    if args.csv:
        with open(args.csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()

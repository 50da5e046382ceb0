"""How often a task's reward gives two clips exactly the same return: the check that each
instruction's tie sentence (`runvocab.instructions.tie_kind`) says what the reward does.

Scripted runs, as the first rounds of every run see them: episodes of random actions (the
exploration phase) and of no action at all (an agent that has learnt to do nothing), cut into
segments of the queries' length every half segment; every pair of segments of one policy is a
query. A pair is an exact tie when both segment returns are equal to the last bit, which the
scripted teacher answers "equally good" (`teacher.tie`).

    .venv/bin/python -m trainer.tie_check                      # every task, a table
    .venv/bin/python -m trainer.tie_check dmc:hopper_hop dmc:cheetah_run
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass

import numpy as np

from runvocab.instructions import tie_kind, tie_sentence
from runvocab.tie_sentences import OFTEN_SHARE, RARE_SHARE

POLICIES = ("random", "idle")


@dataclass(frozen=True)
class TieShares:
    task: str
    pairs: dict[str, int]
    """per policy, the pairs of segments compared"""
    ties: dict[str, int]
    """per policy, the pairs whose returns are exactly equal"""

    def share(self, policy: str) -> float:
        return self.ties[policy] / max(1, self.pairs[policy])

    @property
    def any_share(self) -> float:
        return sum(self.ties.values()) / max(1, sum(self.pairs.values()))

    def measured_kind(self) -> str:
        """The tie sentence the measurement calls for: "often" when most random pairs tie (as
        early in every run), "rare" when almost no pair of either policy does, else
        "sometimes"."""
        if self.share("random") >= OFTEN_SHARE:
            return "often"
        if max(self.share(p) for p in POLICIES) < RARE_SHARE:
            return "rare"
        return "sometimes"


def segments(task: str, policy: str, *, episodes: int, steps: int, segment: int,
             seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(returns (n,), states (n, segment, state size)) of the segments cut from `episodes`
    episodes of `steps` steps."""
    from trainer.envs import make_env

    rng = np.random.default_rng(seed)
    returns, states = [], []
    with make_env(task, seed, episode_length=steps) as env:
        for _ in range(episodes):
            env.reset()
            rewards = np.empty(steps)
            episode = []
            for t in range(steps):
                episode.append(env.physics_state())
                action = (rng.uniform(-1, 1, env.action_dim) if policy == "random"
                          else np.zeros(env.action_dim))
                rewards[t] = env.step(action.astype(np.float32)).reward
            for i in range(0, steps - segment + 1, segment // 2):
                returns.append(float(rewards[i:i + segment].sum()))
                states.append(np.array(episode[i:i + segment]))
    return np.array(returns), np.array(states)


def tie_shares(task: str, *, episodes: int = 2, steps: int = 200, segment: int = 50,
               seed: int = 0) -> TieShares:
    pairs, ties = {}, {}
    for policy in POLICIES:
        r, states = segments(task, policy, episodes=episodes, steps=steps, segment=segment,
                             seed=seed)
        flat = states.reshape(len(r), -1)
        i, j = np.triu_indices(len(r), k=1)
        same = np.array([np.allclose(flat[a], flat[b], rtol=0, atol=1e-6)
                         for a, b in zip(i, j, strict=True)], bool)
        pairs[policy] = int((~same).sum())
        ties[policy] = int(((r[i] == r[j]) & ~same).sum())
    return TieShares(task, pairs, ties)


def main(argv: list[str] | None = None) -> int:
    os.environ.setdefault("MUJOCO_GL", "egl")
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("tasks", nargs="*", help="tasks (default: every installed task)")
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--segment", type=int, default=50)
    args = p.parse_args(argv)
    from runvocab.names import all_tasks

    tasks = args.tasks or all_tasks()
    print(f"{'task':<34} {'random':>7} {'idle':>7}  {'says':<9} {'measured':<9}")
    wrong = []
    for task in tasks:
        s = tie_shares(task, episodes=args.episodes, steps=args.steps, segment=args.segment)
        says, measured = tie_kind(task), s.measured_kind()
        if says != measured:
            wrong.append(task)
        print(f"{task:<34} {s.share('random'):>7.1%} {s.share('idle'):>7.1%}  {says:<9} "
              f"{measured:<9}{'' if says == measured else '  <- ' + tie_sentence(task)}",
              flush=True)
    print(f"{len(tasks) - len(wrong)} of {len(tasks)} tie sentences match the reward"
          + (f"; not: {', '.join(wrong)}" if wrong else ""))
    return 1 if wrong else 0


if __name__ == "__main__":
    sys.exit(main())

"""How much task behaviour a skill snapshot carries: the task return of random skills, against
uniformly random actions.

S-EPOA's premise is that some pretrained skill is already near the task, so that z_task, the
best of N_z random skills under R_theta, starts the agent ahead. This measures the premise on
the snapshot itself, with the true reward and no R_theta: N_z (50) skills drawn from the
backend's prior, one deterministic episode each, and as many episodes of uniform random actions
on the same evaluation env. The summary (median, top-5 mean, maximum of each) is written beside
the snapshot as `<snapshot>.quality.json`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from runvocab.snapshot_names import QUALITY_FORMAT, quality_path
from trainer.envs import Env, make_env
from trainer.skills.agent import SkillAgent
from trainer.skills.common import SkillBackend

EVAL_SEED_OFFSET = 200_000
"""the quality env's seed is the pretraining seed plus this: episodes the pretraining never saw"""
TOP = 5


def summary(returns: list[float]) -> dict[str, float]:
    """median, mean of the best `TOP`, maximum and mean of episode returns."""
    values = np.sort(np.asarray(returns, dtype=np.float64))
    return {"median": float(np.median(values)), f"top{TOP}_mean": float(values[-TOP:].mean()),
            "max": float(values[-1]), "mean": float(values.mean())}


def measure(agent: SkillAgent, backend: SkillBackend, task: str, seed: int,
            episode_length: int | None = None, skills: int = 50) -> dict[str, Any]:
    """Task returns of `skills` random skills (one deterministic episode each) and of `skills`
    episodes of uniform random actions, with their summaries. Its own RNG and env: a
    pretraining that measures along the way goes on exactly as one that does not."""
    if skills < TOP:
        raise ValueError(f"skill quality needs at least {TOP} skills (the top-{TOP} mean), "
                         f"got {skills}")
    rng = np.random.default_rng(seed + EVAL_SEED_OFFSET)
    env = make_env(task, seed + EVAL_SEED_OFFSET, episode_length)
    try:
        drawn = backend.sample_skills(rng, skills)
        skill_returns = [_episode(env, lambda o, z=z: agent.act(o, z, rng, deterministic=True))
                         for z in drawn]
        random_returns = [_episode(env, lambda _o: rng.uniform(-1, 1, env.action_dim))
                          for _ in range(skills)]
    finally:
        env.close()
    best = int(np.argmax(skill_returns))
    return {
        "format": QUALITY_FORMAT, "task": task, "seed": seed, "skills": skills,
        "skill": summary(skill_returns), "random_actions": summary(random_returns),
        "skill_returns": skill_returns, "random_action_returns": random_returns,
        "best_skill": drawn[best].tolist(),
    }


def _episode(env: Env, act: Callable[..., Any]) -> float:
    obs, total, done = env.reset(), 0.0, False
    while not done:
        result = env.step(np.asarray(act(obs), dtype=np.float32))
        obs, total, done = result.obs, total + result.reward, result.done
    return total


def write(snapshot: str, quality: dict[str, Any], steps: int) -> str:
    """Write `quality` of the snapshot at `snapshot` (pretrained `steps` steps) beside it."""
    path = quality_path(snapshot)
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump({"snapshot": os.path.basename(snapshot), "pretrain_steps": steps} | quality,
                  f, indent=1)
    os.replace(tmp, path)
    return path


def read(snapshot: str) -> dict[str, Any] | None:
    """The quality written beside `snapshot`, or None where none was measured."""
    path = quality_path(snapshot)
    if not os.path.exists(path):
        return None
    with open(path) as f:
        data: dict[str, Any] = json.load(f)
    return data if data.get("format") == QUALITY_FORMAT else None


def line(quality: dict[str, Any]) -> str:
    """One line for a terminal: skills against random actions."""
    s, r = quality["skill"], quality["random_actions"]
    return (f"skill quality over {quality['skills']} random skills: median {s['median']:.1f}, "
            f"top-{TOP} mean {s[f'top{TOP}_mean']:.1f}, max {s['max']:.1f}; uniform random "
            f"actions: median {r['median']:.1f}, top-{TOP} mean {r[f'top{TOP}_mean']:.1f}, "
            f"max {r['max']:.1f}")

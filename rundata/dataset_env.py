"""The gymnasium environment a dataset export names, so that offline-RL libraries that recover
it from Minari's `env_spec` (d3rlpy's `get_minari`, `MinariDataset.recover_environment`) can.

    env_spec("dmc:walker_walk", episode_length=1000)

- DMControl: Shimmy's `dm_control/<domain>-<task>-v0` (`pip install "shimmy[dm-control]"`),
  loaded with dm_control's `flat_observation`, which concatenates the observation's parts in
  the task's own order, as the project's environment does (Shimmy's own dict space sorts them
  by name, which reorders walker's, hopper's and most other tasks'), then
  `FlattenObservation` for a Box; without dm_control's own time limit, as the project steps it.
- Metaworld: Metaworld's own MT1 environment (`Meta-World/MT1`, `metaworld.make_mt_envs`) of
  the task, with the goal variants of seed 0, the ones the project's runs draw from.

Both end an episode at the dataset's episode length. The entry points are names, not Python
objects, so that the spec is stored as JSON and nothing of this project is needed to use it.
"""

from __future__ import annotations

from typing import Any

DMC_DOMAINS = ("acrobot", "ball_in_cup", "cartpole", "cheetah", "dog", "finger", "fish",
               "hopper", "humanoid_CMU", "humanoid", "lqr", "manipulator", "pendulum",
               "point_mass", "quadruped", "reacher", "stacker", "swimmer", "walker")
"""dm_control suite domains, longer names first (humanoid_CMU before humanoid)"""
MT1_TASKS_SEED = 0
"""the seed of the MT1 goal variants (`trainer.envs.MT1_TASKS_SEED`)"""
MUJOCO = "mujoco==3.3.0"
REQUIREMENTS = {
    "dmc": [MUJOCO, "dm-control==1.0.28", "shimmy[dm-control]>=2.0"],
    "metaworld": [MUJOCO, "metaworld==3.1.1"],
}
"""per task family, what the environment the spec names needs (Minari's `requirements`,
checked by `recover_environment`)"""


def dmc_gym_id(task: str) -> str | None:
    """Shimmy's id of a `dmc:<domain>_<task>` task, e.g. `dm_control/ball_in_cup-catch-v0`."""
    name = task.removeprefix("dmc:")
    for domain in DMC_DOMAINS:
        if name.startswith(domain + "_"):
            return f"dm_control/{domain}-{name.removeprefix(domain + '_')}-v0"
    return None


def env_spec(task: str, episode_length: int | None) -> Any | None:
    """A gymnasium `EnvSpec` of `task` whose episodes end at `episode_length` steps (None:
    the episodes differ in length, and the environment's own limit applies); None where no
    gymnasium id exists for the task."""
    from gymnasium.envs.registration import EnvSpec, WrapperSpec

    if task.startswith("dmc:"):
        gym_id = dmc_gym_id(task)
        if gym_id is None:
            return None
        return EnvSpec(
            id=gym_id, entry_point="gymnasium:make", max_episode_steps=episode_length,
            kwargs={"id": f"shimmy:{gym_id}", "environment_kwargs": {"flat_observation": True},
                    "task_kwargs": {"time_limit": float("inf")}},
            additional_wrappers=(WrapperSpec(
                name="FlattenObservation",
                entry_point="gymnasium.wrappers:FlattenObservation", kwargs={}),))
    if task.startswith("metaworld:"):
        name = task.removeprefix("metaworld:") + "-v3"
        kwargs: dict[str, Any] = {"name": name, "seed": MT1_TASKS_SEED}
        if episode_length is not None:
            kwargs["max_episode_steps"] = episode_length
        return EnvSpec(id="Meta-World/MT1", entry_point="metaworld:make_mt_envs",
                       max_episode_steps=episode_length, kwargs=kwargs)
    return None


def requirements(task: str) -> list[str]:
    """Minari's `requirements` for a dataset of `task`: what its environment needs."""
    return list(REQUIREMENTS["metaworld" if task.startswith("metaworld:") else "dmc"])

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported; the project default

import json

import numpy as np
import pytest

from runvocab.names import all_tasks, tasks_by_family
from trainer.envs import (
    DMCEnv,
    MetaworldEnv,
    StepResult,
    UnknownTaskError,
    installed_tasks,
    make_env,
)

PAPER_TASKS = [
    "dmc:cheetah_run", "dmc:walker_run", "dmc:quadruped_walk", "dmc:quadruped_run",
    "metaworld:door-open", "metaworld:button-press", "metaworld:window-open",
]


@pytest.fixture
def make():
    """make_env, closing every env made at the end of the test."""
    envs = []

    def _make(task: str, seed: int, episode_length: int | None = None):
        env = make_env(task, seed, episode_length)
        envs.append(env)
        return env

    yield _make
    for env in envs:
        env.close()


def random_actions(env, n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (n, env.action_dim)).astype(np.float32)


def rollout(env, actions: np.ndarray, render_every: int = 0, size: tuple[int, int] = (64, 48)):
    """Random-action run from a reset, resetting at episode ends. Returns, for every observed
    state, (physics state, episode context, observation, frame or None)."""
    obs = env.reset()
    records = []
    for t, action in enumerate(actions):
        frame = env.render(*size) if render_every and t % render_every == 0 else None
        records.append((env.physics_state(), env.episode_context(), obs, frame))
        result = env.step(action)
        obs = env.reset() if result.done else result.obs
    return records


# ---------------------------------------------------------------------------------------------
# interface


@pytest.mark.parametrize("task, cls, obs_dim, action_dim", [
    ("dmc:cheetah_run", DMCEnv, 17, 6),
    ("metaworld:door-open", MetaworldEnv, 39, 4),
])
def test_interface_and_episode_end(make, task, cls, obs_dim, action_dim):
    env = make(task, 0, episode_length=30)
    assert isinstance(env, cls)
    assert (env.task, env.obs_dim, env.action_dim, env.episode_length) == (
        task, obs_dim, action_dim, 30)
    with pytest.raises(RuntimeError):  # no episode yet
        env.step(np.zeros(action_dim, np.float32))

    obs = env.reset()
    assert obs.dtype == np.float32 and obs.shape == (obs_dim,)
    for t, action in enumerate(random_actions(env, 30), start=1):
        state = env.physics_state()
        assert state.dtype == np.float64 and state.ndim == 1
        result = env.step(action)
        assert isinstance(result, StepResult)
        assert result.obs.dtype == np.float32 and result.obs.shape == (obs_dim,)
        assert type(result.reward) is float and np.isfinite(result.reward)
        assert type(result.success) is bool
        assert result.done == (t == 30), t
    with pytest.raises(RuntimeError):  # the episode is over
        env.step(np.zeros(action_dim, np.float32))
    assert env.reset().shape == (obs_dim,)
    with pytest.raises(ValueError):
        env.step(np.zeros(action_dim + 1, np.float32))
    env.step([0.0] * action_dim)  # any array-like of the right length


def test_default_episode_lengths(make):
    assert make("dmc:cheetah_run", 0).episode_length == 1000
    assert make("metaworld:door-open", 0).episode_length == 500
    with pytest.raises(ValueError):
        make_env("dmc:cheetah_run", 0, episode_length=0)


@pytest.mark.parametrize("task, length", [("dmc:cheetah_run", 1000),
                                          ("metaworld:door-open", 510)])
def test_done_exactly_at_episode_length(make, task, length):
    # 510 > Metaworld's own max_path_length of 500, which must not end or break the episode.
    env = make(task, 0, episode_length=None if task.startswith("dmc") else length)
    env.reset()
    dones = [env.step(a).done for a in random_actions(env, length)]
    assert dones[-1] and not any(dones[:-1])


def test_dmc_context_is_zero_and_metaworld_context_is_a_variant(make):
    dmc, mw = make("dmc:cheetah_run", 0), make("metaworld:door-open", 0, episode_length=5)
    dmc.reset()
    assert dmc.episode_context() == 0
    contexts = set()
    for _ in range(4):
        mw.reset()
        context = mw.episode_context()
        for a in random_actions(mw, 5):
            mw.step(a)
            assert mw.episode_context() == context  # fixed for the whole episode
        contexts.add(context)
    assert contexts <= set(range(50)) and len(contexts) > 1


# ---------------------------------------------------------------------------------------------
# determinism and RNG state


@pytest.mark.parametrize("task", ["dmc:cheetah_run", "metaworld:door-open"])
def test_same_seed_same_trajectory(make, task):
    a, b = make(task, 7, episode_length=15), make(task, 7, episode_length=15)
    actions = random_actions(a, 40)
    runs = zip(rollout(a, actions), rollout(b, actions), strict=True)
    for (sa, ca, oa, _), (sb, cb, ob, _) in runs:
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(sa, sb)
        assert ca == cb


def test_different_seed_different_reset(make):
    a, b = make("dmc:cheetah_run", 0), make("dmc:cheetah_run", 1)
    assert not np.array_equal(a.reset(), b.reset())


@pytest.mark.parametrize("task", ["dmc:cheetah_run", "metaworld:door-open"])
def test_rng_state_resumes_at_episode_boundary(make, task):
    a = make(task, 3, episode_length=10)
    a.reset()
    for action in random_actions(a, 10, seed=1):
        a.step(action)
    saved = json.loads(json.dumps(a.rng_state()))  # JSON-able, and survives a round trip
    actions = random_actions(a, 30, seed=2)
    expected = rollout(a, actions)

    b = make(task, 99, episode_length=10)  # another seed: the RNG state alone must decide
    b.set_rng_state(saved)
    for (_, ca, oa, _), (_, cb, ob, _) in zip(expected, rollout(b, actions), strict=True):
        np.testing.assert_array_equal(oa, ob)
        assert ca == cb


# ---------------------------------------------------------------------------------------------
# physics state and restore


@pytest.mark.parametrize("task", [
    "dmc:cheetah_run",
    "dmc:quadruped_walk",  # force/torque/accelerometer sensors in the observation
    "dmc:reacher_easy",  # the target is moved in the model each episode
    "metaworld:door-open",
    "metaworld:window-close",  # Metaworld's own reset observation is stale here
])
def test_restore_reproduces_observations_on_a_fresh_env(make, task):
    env = make(task, 1, episode_length=12)
    records = rollout(env, random_actions(env, 30))
    if task.startswith("metaworld"):  # three episodes: restore has to switch variants
        assert len({context for _, context, _, _ in records}) > 1

    fresh = make(task, 2, episode_length=12)
    fresh.reset()
    for t, (state, context, obs, _) in enumerate(records):
        np.testing.assert_array_equal(fresh.restore(state, context), obs, err_msg=f"step {t}")
        assert fresh.episode_context() == context
        np.testing.assert_array_equal(fresh.physics_state(), state)


def test_restore_rejects_bad_input(make):
    env = make("metaworld:door-open", 0)
    env.reset()
    state = env.physics_state()
    with pytest.raises(ValueError):
        env.restore(state[:-1], env.episode_context())
    with pytest.raises(ValueError):
        env.restore(state, 50)
    escape = make("dmc:quadruped_escape", 0)
    escape.reset()
    with pytest.raises(NotImplementedError):  # its random terrain is not in the state
        escape.restore(escape.physics_state(), 0)


# ---------------------------------------------------------------------------------------------
# rendering


@pytest.mark.parametrize("task", ["dmc:cheetah_run", "metaworld:door-open"])
def test_render_matches_after_restore(make, task):
    env = make(task, 0, episode_length=20)
    records = rollout(env, random_actions(env, 12), render_every=5)
    frames = [(s, c, f) for s, c, _, f in records if f is not None]
    assert len(frames) == 3
    for _, _, frame in frames:
        assert frame.dtype == np.uint8 and frame.shape == (48, 64, 3)
        assert frame.std() > 5  # not a blank image
    assert not np.array_equal(frames[0][2], frames[-1][2])  # it moved

    fresh = make(task, 5, episode_length=20)
    for state, context, frame in frames:
        fresh.restore(state, context)
        np.testing.assert_array_equal(fresh.render(64, 48), frame)


def test_render_cameras(make):
    quadruped = make("dmc:quadruped_walk", 0)
    quadruped.reset()
    np.testing.assert_array_equal(quadruped.render(32, 32), quadruped.render(32, 32, camera=2))
    door = make("metaworld:door-open", 0)
    door.reset()
    np.testing.assert_array_equal(door.render(32, 32), door.render(32, 32, camera="corner"))
    assert door.render(40, 24, camera="topview").shape == (24, 40, 3)
    with pytest.raises(ValueError, match="corner"):  # the message lists the cameras
        door.render(32, 32, camera="nope")


# ---------------------------------------------------------------------------------------------
# task names


@pytest.mark.parametrize("name", [
    "dmc:cheetah_fly", "metaworld:nope", "gym:Pendulum", "cheetah_run", "metaworld:door-open-v3",
])
def test_unknown_task_names(name):
    with pytest.raises(UnknownTaskError) as err:
        make_env(name, 0)
    message = str(err.value)
    assert repr(name) in message
    assert any(task in message for task in PAPER_TASKS)
    assert isinstance(err.value, ValueError)


def test_task_list_matches_the_installed_suites():
    """runvocab/tasks.json is data the server reads without MuJoCo; it must name exactly the
    installed tasks (rewrite it with `python -m trainer.envs` after upgrading a suite)."""
    installed = installed_tasks()
    assert tasks_by_family() == {family: tuple(names) for family, names in installed.items()}
    tasks = all_tasks()
    assert set(PAPER_TASKS) <= set(tasks)
    assert len(tasks) == len(set(tasks))
    assert "dmc:ball_in_cup_catch" in tasks and "dmc:humanoid_CMU_run" in tasks
    assert sum(t.startswith("metaworld:") for t in tasks) == 50
    assert not any(t.endswith("-v3") for t in tasks)

"""One environment interface over DMControl suite tasks and Metaworld v3 MT1 tasks.

Task names are "dmc:<domain>_<task>" (any task of `dm_control.suite.ALL_TASKS`) and
"metaworld:<name>" (any MT1 v3 env, without the "-v3" suffix). Every env counts its own steps:
an episode is exactly `episode_length` steps and the last one has `done=True`; early termination
of the underlying libraries is ignored.

`physics_state()` and `episode_context()` together capture everything that the current
observation and frame depend on, so `restore()` on a fresh env of the same task (any seed)
reproduces the observation bit for bit and renders the same frame:

- DMC: qpos, qvel, act; the readings of acceleration-stage sensors (touch, force, torque,
  accelerometer), which dm_control's step leaves at their pre-integration values, so a
  re-computation from the state alone would differ; and the few model entries that some tasks
  move per episode (reacher's target, ...). The context is always 0. quadruped_escape's random
  terrain is too large to store per step, so that one task cannot be restored.
- Metaworld: qpos, qvel, mocap pose, and the "previous frame" half of the observation (Metaworld
  frame-stacks). The context is the index of the MT1 goal variant, drawn per episode from the
  env's seeded RNG (-1 before the first reset); restoring another variant re-runs its reset,
  which re-applies its edits to the model (object and goal placement). The goal is visible in
  the observation, as in MT1. reset() recomputes its observation from the state (a few Metaworld
  resets return a stale one) and clips it as step() does.

`restore()` does not touch the episode step counter. Frames are drawn by the env's
`trainer.scene.Scene`.
"""

from __future__ import annotations

import abc
import functools
import json
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from runvocab.names import TASKS_JSON, unknown_task
from trainer.scene import MotionCues, Scene

DMC_PREFIX = "dmc:"
METAWORLD_PREFIX = "metaworld:"
DMC_EPISODE_LENGTH = 1000
METAWORLD_EPISODE_LENGTH = 500
# Fixed rather than the run's seed, so that variant index i is the same goal in every run and
# process (a stored (state, context) pair restores on any env of the task).
MT1_TASKS_SEED = 0
METAWORLD_DEFAULT_CAMERA = "corner"
# URLB's choice: quadruped's camera 0 is a distant global view, 2 follows the body.
_DMC_DEFAULT_CAMERA = {"quadruped": 2}
# Model entries that tasks set per episode (initialize_episode) or per seed (lqr's stiffness):
# field, object type (None: the whole array) and object names (those missing are skipped).
_DMC_EPISODE_MODEL_FIELDS: dict[str, tuple[tuple[str, str | None, tuple[str, ...]], ...]] = {
    "finger": (("site_pos", "site", ("target",)),),
    "fish": (("geom_pos", "geom", ("target",)),),
    "lqr": (("jnt_stiffness", None, ()),),
    "manipulator": (
        ("body_pos", "body", ("target_ball", "target_peg", "cup", "slot")),
        ("body_quat", "body", ("target_ball", "target_peg", "cup", "slot")),
    ),
    "point_mass": (("wrap_prm", None, ()),),
    "reacher": (("geom_pos", "geom", ("target",)),),
    "stacker": (("body_pos", "body", ("target",)),),
    "swimmer": (("geom_pos", "geom", ("target",)), ("light_pos", "light", ("target_light",))),
}
_DMC_UNRESTORABLE = {("quadruped", "escape")}


class UnknownTaskError(ValueError):
    """A task name that is not one of `installed_tasks()`."""


@dataclass(frozen=True, slots=True)
class StepResult:
    obs: np.ndarray
    """float32, flat"""
    reward: float
    """ground-truth reward (for teachers and evaluation only)"""
    success: bool
    """Metaworld's info["success"]; always False on DMC"""
    done: bool
    """True on the last step of the episode (time limit reached)"""


# ---------------------------------------------------------------------------------------------
# Task names


def _quadruped_sensor_names(self: Any, *sensor_types: int) -> list[str]:
    # dm_control 1.0.28's version calls np.in1d, which numpy 2.4 removed; same logic, np.isin.
    try:
        return self._sensor_types_to_names[sensor_types]
    except KeyError:
        [ids] = np.where(np.isin(self.model.sensor_type, sensor_types))
        names = [self.model.id2name(i, "sensor") for i in ids]
        self._sensor_types_to_names[sensor_types] = names
        return names


@functools.cache
def _dmc_suite() -> Any:
    # Imported on first use: dm_control and metaworld each take about a second to import.
    from dm_control import suite
    from dm_control.suite import quadruped

    quadruped.Physics._get_sensor_names = _quadruped_sensor_names
    return suite


@functools.cache
def _dmc_tasks() -> dict[str, tuple[str, str]]:
    """"<domain>_<task>" -> (domain, task); domains may contain "_", hence the lookup table."""
    return {f"{domain}_{task}": (domain, task) for domain, task in _dmc_suite().ALL_TASKS}


@functools.cache
def _metaworld_tasks() -> tuple[str, ...]:
    import metaworld

    return tuple(name.removesuffix("-v3") for name in metaworld.MT1.ENV_NAMES)


@functools.cache
def _mt1(name: str) -> tuple[type, tuple[Any, ...]]:
    """The env class and the 50 goal variants (MT1 train tasks) of one Metaworld task."""
    import metaworld

    benchmark = metaworld.MT1(f"{name}-v3", seed=MT1_TASKS_SEED)
    return benchmark.train_classes[f"{name}-v3"], tuple(benchmark.train_tasks)


def installed_tasks() -> dict[str, list[str]]:
    """Every task of the installed dm_control and Metaworld, per family: what
    `runvocab/tasks.json` must hold (`python -m trainer.envs` rewrites it)."""
    return {"dmc": [DMC_PREFIX + n for n in _dmc_tasks()],
            "metaworld": [METAWORLD_PREFIX + n for n in _metaworld_tasks()]}


def make_env(task: str, seed: int, episode_length: int | None = None) -> Env:
    if episode_length is not None and episode_length < 1:
        raise ValueError(f"episode_length must be at least 1, got {episode_length}")
    if task.startswith(DMC_PREFIX):
        name = task.removeprefix(DMC_PREFIX)
        if name not in _dmc_tasks():
            raise UnknownTaskError(unknown_task(task))
        return DMCEnv(name, seed, episode_length or DMC_EPISODE_LENGTH)
    if task.startswith(METAWORLD_PREFIX):
        name = task.removeprefix(METAWORLD_PREFIX)
        if name not in _metaworld_tasks():
            raise UnknownTaskError(unknown_task(task))
        return MetaworldEnv(name, seed, episode_length or METAWORLD_EPISODE_LENGTH)
    raise UnknownTaskError(unknown_task(task))


# ---------------------------------------------------------------------------------------------
# Environments


class Env(abc.ABC):
    """The shared surface; `DMCEnv` and `MetaworldEnv` fill in the simulator-specific parts."""

    task: str
    obs_dim: int
    action_dim: int
    episode_length: int

    def __init__(self, task: str, episode_length: int, model: mujoco.MjModel,
                 data: mujoco.MjData, action_low: np.ndarray, action_high: np.ndarray,
                 default_camera: int | str) -> None:
        self.task, self.episode_length = task, episode_length
        self.action_dim = len(action_low)
        self._model, self._data = model, data
        self._steps_left = 0  # step() before the first reset() is an error
        # Affine map from [-1, 1] to the native bounds (None: they are [-1, 1] already).
        # Unlimited actuators (lqr's) get the action as it is.
        bounded = (action_low > -mujoco.mjMAXVAL) & (action_high < mujoco.mjMAXVAL)
        low, high = np.where(bounded, action_low, -1.0), np.where(bounded, action_high, 1.0)
        unit = bool(np.all(low == -1) and np.all(high == 1))
        self._action_scale = None if unit else (high - low) / 2
        self._action_offset = None if unit else (high + low) / 2
        self._scene = Scene(task, model, data, default_camera)
        self._closed = False

    # -- the simulator-specific parts
    @abc.abstractmethod
    def _reset(self) -> np.ndarray: ...

    @abc.abstractmethod
    def _step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool]: ...

    @abc.abstractmethod
    def physics_state(self) -> np.ndarray:
        """float64 flat vector: everything the current observation and frame depend on."""

    @abc.abstractmethod
    def episode_context(self) -> int:
        """What varies per episode outside the physics state (Metaworld's goal variant)."""

    @abc.abstractmethod
    def restore(self, state: np.ndarray, context: int) -> np.ndarray:
        """Set the simulator to `state` in `context`; returns the observation recorded there."""

    @abc.abstractmethod
    def rng_state(self) -> dict:
        """All RNG state of the env, as JSON-able plain data."""

    @abc.abstractmethod
    def set_rng_state(self, state: dict) -> None: ...

    @abc.abstractmethod
    def _close(self) -> None: ...

    # -- shared
    def reset(self) -> np.ndarray:
        obs = self._reset()
        self._steps_left = self.episode_length
        return obs

    def step(self, action: np.ndarray) -> StepResult:
        if self._steps_left <= 0:
            raise RuntimeError(f"{self.task}: the episode is over (or never started); call reset()")
        if np.shape(action) != (self.action_dim,):
            raise ValueError(f"{self.task}: action shape {np.shape(action)}, "
                             f"expected ({self.action_dim},)")
        # No clipping here (it would cost ~10% of a cheetah step): MuJoCo clamps the controls of
        # limited actuators to their range, which is the native image of [-1, 1].
        if self._action_scale is not None and self._action_offset is not None:
            action = action * self._action_scale + self._action_offset
        obs, reward, success = self._step(action)
        self._steps_left -= 1
        return StepResult(obs, reward, success, self._steps_left == 0)

    # -- frames, drawn by the env's `trainer.scene.Scene`
    def render(self, width: int, height: int, camera: int | str | None = None) -> np.ndarray:
        """uint8 (height, width, 3) off-screen frame of the current state. Cameras by index or
        name; None: DMC's camera 0 (2 for quadruped), Metaworld's "corner" (turned upright)."""
        return self._scene.render(width, height, camera)

    def segmentation(self, width: int, height: int,
                     camera: int | str | None = None) -> np.ndarray:
        """int32 (height, width, 2): per pixel of render()'s frame, the MuJoCo object id and
        type it shows; (-1, -1) where nothing is drawn (`Scene.segmentation`)."""
        return self._scene.segmentation(width, height, camera)

    def floor_geoms(self) -> np.ndarray:
        """The geom ids of the world's floor planes (those motion cues move and widen)."""
        return self._scene.floor_geoms()

    def set_motion_cues(self, cues: MotionCues | None) -> None:
        """What render() adds so that a clip shows motion wherever the agent is (`MotionCues`);
        None: the model's scene as it is."""
        self._scene.set_motion_cues(cues)

    def set_render_quality(self, **quality: int) -> None:
        """Sets fields of the model's `vis.quality` (shadowsize, offsamples, numslices, ...)
        for render() (`Scene.set_render_quality`)."""
        self._scene.set_render_quality(**quality)

    def set_reflections(self, on: bool) -> None:
        """Mirror images in reflective floors (DMC's grid) in render(), or not
        (`Scene.set_reflections`)."""
        self._scene.set_reflections(on)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._scene.close()
        self._close()

    def __enter__(self) -> Env:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.task!r}, episode_length={self.episode_length})"


class DMCEnv(Env):
    """A dm_control suite task, stepped without dm_control's time limit."""

    def __init__(self, name: str, seed: int, episode_length: int) -> None:
        domain, task = _dmc_tasks()[name]
        # No time limit: we end episodes ourselves, and at its own limit dm_control would
        # silently reset on the next step.
        self._env = _dmc_suite().load(
            domain, task, task_kwargs={"random": seed, "time_limit": float("inf")}
        )
        self._physics, self._task = self._env.physics, self._env.task
        self._n_sub_steps = round(self._env.control_timestep() / self._physics.timestep())
        model, data = self._physics.model.ptr, self._physics.data.ptr
        spec = self._env.action_spec()
        camera = _DMC_DEFAULT_CAMERA.get(domain, 0 if model.ncam else -1)
        super().__init__(DMC_PREFIX + name, episode_length, model, data,
                         spec.minimum.astype(np.float64), spec.maximum.astype(np.float64), camera)
        self.obs_dim = sum(int(np.prod(s.shape)) for s in self._env.observation_spec().values())
        self._restorable = (domain, task) not in _DMC_UNRESTORABLE

        acc = [np.arange(model.sensor_adr[i], model.sensor_adr[i] + model.sensor_dim[i])
               for i in range(model.nsensor)
               if model.sensor_needstage[i] == mujoco.mjtStage.mjSTAGE_ACC]
        self._acc_sensors = np.concatenate(acc) if acc else np.zeros(0, np.int64)
        # (model array, rows) of the per-episode model entries, stored after the data part.
        self._model_entries: list[tuple[np.ndarray, np.ndarray]] = []
        for field, obj, names in _DMC_EPISODE_MODEL_FIELDS.get(domain, ()):
            array = getattr(model, field)
            if obj is None:
                rows = np.arange(len(array))
            else:
                obj_type = getattr(mujoco.mjtObj, f"mjOBJ_{obj.upper()}")
                ids = (mujoco.mj_name2id(model, obj_type, n) for n in names)
                rows = np.array([i for i in ids if i >= 0], np.int64)
            if len(rows):
                self._model_entries.append((array, rows))
        self._state_dim = (model.nq + model.nv + model.na + len(self._acc_sensors)
                           + sum(a[r].size for a, r in self._model_entries))

    def _observation(self) -> np.ndarray:
        obs = self._task.get_observation(self._physics)  # an OrderedDict in a fixed key order
        return np.concatenate([np.ravel(v) for v in obs.values()], dtype=np.float32)

    def _reset(self) -> np.ndarray:
        self._env.reset()
        return self._observation()

    def _step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool]:
        # control.Environment.step without its step counting and auto-reset.
        self._task.before_step(action, self._physics)
        self._physics.step(self._n_sub_steps)
        self._task.after_step(self._physics)
        return self._observation(), float(self._task.get_reward(self._physics)), False

    def physics_state(self) -> np.ndarray:
        d = self._data
        if self._state_dim == self._model.nq + self._model.nv + self._model.na:
            return np.concatenate([d.qpos, d.qvel, d.act])  # the common case, a little faster
        return np.concatenate([d.qpos, d.qvel, d.act, d.sensordata[self._acc_sensors],
                               *(a[r].ravel() for a, r in self._model_entries)])

    def episode_context(self) -> int:
        return 0

    def restore(self, state: np.ndarray, context: int) -> np.ndarray:
        if not self._restorable:
            raise NotImplementedError(f"{self.task}: the per-episode terrain is not part of the "
                                      "physics state, so states cannot be restored")
        state = np.asarray(state, np.float64)
        if state.shape != (self._state_dim,) or context != 0:
            raise ValueError(f"{self.task}: expected a ({self._state_dim},) state and context 0, "
                             f"got {state.shape} and {context}")
        m, d = self._model, self._data
        pos = m.nq + m.nv + m.na
        n_acc = len(self._acc_sensors)
        end = pos + n_acc
        for array, rows in self._model_entries:  # the model first: forward() depends on it
            size = array[rows].size
            array[rows] = state[end:end + size].reshape(array[rows].shape)
            end += size
        d.qpos[:], d.qvel[:] = state[:m.nq], state[m.nq:m.nq + m.nv]
        d.act[:] = state[m.nq + m.nv:pos]
        self._physics.forward()
        d.sensordata[self._acc_sensors] = state[pos:pos + n_acc]
        return self._observation()

    def rng_state(self) -> dict:
        s = self._task.random.get_state(legacy=False)
        return {"task_random": {"bit_generator": s["bit_generator"],
                                "key": s["state"]["key"].tolist(), "pos": int(s["state"]["pos"]),
                                "has_gauss": int(s["has_gauss"]), "gauss": float(s["gauss"])}}

    def set_rng_state(self, state: dict) -> None:
        s = state["task_random"]
        self._task.random.set_state({
            "bit_generator": s["bit_generator"],
            "state": {"key": np.asarray(s["key"], np.uint32), "pos": s["pos"]},
            "has_gauss": s["has_gauss"], "gauss": s["gauss"],
        })

    def _close(self) -> None:
        self._env.close()


class MetaworldEnv(Env):
    """A Metaworld v3 task with MT1's 50 goal variants, one drawn per episode."""

    def __init__(self, name: str, seed: int, episode_length: int) -> None:
        env_cls, self._variants = _mt1(name)
        self._env = env = env_cls()
        env.seed(seed)
        # We end episodes ourselves; Metaworld raises once curr_path_length reaches its 500.
        env.max_path_length = np.iinfo(np.int64).max
        # MT1's observability (the goal is visible) comes with the task; set one now so that
        # the observation bounds are final. Its reset is applied on reset() or restore().
        env.set_task(self._variants[0])
        space = env.sawyer_observation_space
        self._obs_low, self._obs_high = space.low, space.high
        self._variant = -1  # no variant applied yet
        self._variant_rng = np.random.default_rng(seed)
        super().__init__(METAWORLD_PREFIX + name, episode_length, env.model, env.data,
                         env.action_space.low.astype(np.float64),
                         env.action_space.high.astype(np.float64), METAWORLD_DEFAULT_CAMERA)
        self.obs_dim = len(self._obs_low)
        self._prev_frame = env._prev_obs  # the previous-frame half the current obs was built with
        m = self._model
        self._state_splits = np.cumsum([m.nq, m.nv, 3 * m.nmocap, 4 * m.nmocap])
        self._state_dim = int(self._state_splits[-1]) + len(self._prev_frame)

    def _apply_variant(self, index: int) -> np.ndarray:
        env = self._env
        env.set_task(self._variants[index])
        env.reset()
        self._variant = index
        # Some resets (window-close, drawer-open, ...) move joints after their last kinematics
        # update and so return a stale observation; recompute it from the state, as restore()
        # does. The previous-frame half of a first observation is the current frame.
        mujoco.mj_forward(self._model, self._data)
        return self._observe(env._get_curr_obs_combined_no_goal())

    def _observe(self, prev_frame: np.ndarray) -> np.ndarray:
        """The observation of the current (forwarded) state, built as Metaworld's step() does."""
        self._env._prev_obs = self._prev_frame = prev_frame
        obs = self._env._get_obs()  # this moves _prev_obs on to the current frame, as step() does
        return np.clip(obs, self._obs_low, self._obs_high).astype(np.float32)

    def _reset(self) -> np.ndarray:
        return self._apply_variant(int(self._variant_rng.integers(len(self._variants))))

    def _step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool]:
        prev_frame = self._env._prev_obs  # step() replaces it, after building obs with it
        obs, reward, _, _, info = self._env.step(action)
        self._prev_frame = prev_frame
        return obs.astype(np.float32), float(reward), bool(info["success"])

    def physics_state(self) -> np.ndarray:
        d = self._data
        return np.concatenate([d.qpos, d.qvel, d.mocap_pos.ravel(), d.mocap_quat.ravel(),
                               self._prev_frame])

    def episode_context(self) -> int:
        return self._variant

    def restore(self, state: np.ndarray, context: int) -> np.ndarray:
        state = np.asarray(state, np.float64)
        if state.shape != (self._state_dim,) or not 0 <= context < len(self._variants):
            raise ValueError(f"{self.task}: expected a ({self._state_dim},) state and a context "
                             f"in [0, {len(self._variants)}), got {state.shape} and {context}")
        if context != self._variant:
            self._apply_variant(context)
        d = self._data
        qpos, qvel, mocap_pos, mocap_quat, prev_frame = np.split(state, self._state_splits)
        d.qpos[:], d.qvel[:] = qpos, qvel
        d.mocap_pos[:], d.mocap_quat[:] = mocap_pos.reshape(-1, 3), mocap_quat.reshape(-1, 4)
        mujoco.mj_forward(self._model, d)
        return self._observe(prev_frame.copy())

    def rng_state(self) -> dict:
        return {"variant_rng": self._variant_rng.bit_generator.state,
                "np_random": self._env.np_random.bit_generator.state}

    def set_rng_state(self, state: dict) -> None:
        self._variant_rng.bit_generator.state = state["variant_rng"]
        self._env.np_random.bit_generator.state = state["np_random"]

    def _close(self) -> None:
        self._env.close()


if __name__ == "__main__":
    with open(TASKS_JSON, "w") as f:
        json.dump(installed_tasks(), f, indent=1)
        f.write("\n")
    print(f"wrote {TASKS_JSON}")

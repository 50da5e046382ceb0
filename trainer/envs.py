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

`restore()` does not touch the episode step counter.
"""

from __future__ import annotations

import abc
import atexit
import functools
import json
import weakref
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from runvocab.names import TASKS_JSON, unknown_task

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
# Rendering

_open_renderers: weakref.WeakSet[mujoco.Renderer] = weakref.WeakSet()


def _close_open_renderers() -> None:
    for renderer in list(_open_renderers):
        renderer.close()


@functools.cache
def _close_renderers_at_exit() -> None:
    # Registered after the first renderer made its GL context, so after the backend's own exit
    # hook (EGL terminates its display), which therefore runs later: closing first avoids errors.
    atexit.register(_close_open_renderers)


def _upside_down_cameras(model: mujoco.MjModel) -> frozenset[int]:
    """Fixed world cameras whose image "up" points down (Metaworld's corner cameras)."""
    return frozenset(
        i for i in range(model.ncam)
        if model.cam_mode[i] == mujoco.mjtCamLight.mjCAMLIGHT_FIXED and model.cam_bodyid[i] == 0
        and model.cam_mat0[i, 7] < 0  # z component of the camera's y axis
    )


@dataclass(frozen=True, slots=True)
class MotionCues:
    """What a clip's frames show besides the model, so that speed and direction can be seen
    however far the agent has gone (`Env.set_motion_cues`). MuJoCo's planes collide as if
    infinite but are drawn at their `size`: DMC's floors end 2 m behind the start (cheetah,
    walker, hopper) and 15-200 m ahead, and a tracking camera past either end films the body in
    front of the skybox, which moves with the camera, so no motion shows at all."""

    ground_follows: bool = True
    """each floor plane of the world is drawn moved under the camera's subject by a whole number
    of its texture's periods: the same grid, fixed in the world, in every frame"""
    marker_row: float | None = None
    """y (m) of a row of posts beside the track, one every `marker_spacing` m along x, fixed in
    the world (None: no posts; for planar runners filmed from the side)"""
    marker_spacing: float = 1.0
    """metres between two posts; every 5th post is taller and yellow, the one at x = 0 (where
    every episode starts) tallest and red"""
    marker_span: float = 8.0
    """posts are drawn this far (m) either side of the camera's subject"""
    ground_reach: float | None = None
    """each floor with a uniform grid is drawn this far (m) either side of the subject it follows
    (`ground_follows`), across the track as along it, so that a camera filming from the side
    sees ground from the bottom of the frame to the horizon rather than the skybox under a
    narrow track (None: the floors' own sizes; planes collide as infinite whatever size they
    are drawn at)"""
    sky_rgb: tuple[float, float, float] | None = None
    """the skybox drawn in this one colour (0-1 each): DMC's starfield moves with a following
    camera, a motion nobody should judge by (None: the model's own)"""
    camera_distance: float | None = None
    """a camera that follows a subject is moved along its line of sight to this distance (m)
    from it, so that the body fills the share of the frame its task's clips are made for (None:
    where the model puts it)"""


@dataclass(frozen=True, slots=True)
class _Floor:
    geom: int
    center: np.ndarray
    """(x, y) of the plane's centre in the model"""
    size: np.ndarray
    """(x, y) half sizes and the side of the squares it is drawn in, as modelled"""
    period: np.ndarray
    """(x, y) distances the plane can move by and look the same"""
    uniform: bool
    """its grid keeps its scale at any size (a texture stretched over the plane does not)"""


def _floor_planes(model: mujoco.MjModel) -> tuple[_Floor, ...]:
    """Finite, horizontal, unrotated planes of the world body: the floors."""
    floors = []
    for i in range(model.ngeom):
        if (model.geom_type[i] != mujoco.mjtGeom.mjGEOM_PLANE or model.geom_bodyid[i] != 0
                or not np.all(model.geom_size[i, :2] > 0)):
            continue
        quat = model.geom_quat[i]
        if not np.allclose(np.abs(quat), [1, 0, 0, 0]):
            continue
        size = model.geom_size[i, :2]
        mat = int(model.geom_matid[i])
        uniform = mat < 0 or bool(model.mat_texuniform[mat])
        if mat >= 0:
            repeat = np.maximum(model.mat_texrepeat[mat], 1e-9)
            # A uniform texture repeats `texrepeat` times per 2 m of plane (one checker square
            # per metre at texrepeat 1); otherwise it is stretched over the whole plane.
            period = 2 / repeat if uniform else 2 * size / repeat
        else:
            period = np.array([1.0, 1.0])
        floors.append(_Floor(i, model.geom_pos[i, :2].copy(), model.geom_size[i].copy(),
                             np.asarray(period, np.float64), uniform))
    return tuple(floors)


_POST_RGBA = {"metre": (0.85, 0.85, 0.85, 1.0), "five": (1.0, 0.85, 0.1, 1.0),
              "start": (0.9, 0.2, 0.2, 1.0)}
_POST_HALF_HEIGHT = {"metre": 0.08, "five": 0.16, "start": 0.3}


def _add_distance_markers(scene: mujoco.MjvScene, focus_x: float, cues: MotionCues) -> None:
    """Posts every `cues.marker_spacing` m along x at y = `cues.marker_row`, within
    `cues.marker_span` of focus_x, added to the scene as decoration."""
    step = cues.marker_spacing
    first = int(np.floor((focus_x - cues.marker_span) / step))
    last = int(np.ceil((focus_x + cues.marker_span) / step))
    eye = np.eye(3).ravel()
    for k in range(first, last + 1):
        if scene.ngeom >= scene.maxgeom:
            return
        kind = "start" if k == 0 else "five" if k % 5 == 0 else "metre"
        half = _POST_HALF_HEIGHT[kind]
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_BOX, np.array([0.02, 0.02, half]),
                            np.array([k * step, cues.marker_row, half]), eye,
                            np.array(_POST_RGBA[kind], np.float32))
        geom.category = mujoco.mjtCatBit.mjCAT_DECOR
        geom.objtype, geom.objid = mujoco.mjtObj.mjOBJ_UNKNOWN, -1  # left unset by initGeom
        geom.segid = scene.ngeom  # as mjv_updateScene numbers its own
        scene.ngeom += 1


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
        self._default_camera = default_camera
        self._upside_down = _upside_down_cameras(model)
        self._renderers: dict[tuple[int, int] | tuple[int, int, str], mujoco.Renderer] = {}
        self._reflectance: np.ndarray | None = None  # the model's own, once reflections are set
        self._floors = _floor_planes(model)
        self._cues: MotionCues | None = None  # set_motion_cues()
        self._sky: np.ndarray | None = None  # the skybox's own texels, once painted
        self._sky_rgb: tuple[float, float, float] | None = None  # the colour painted, if any
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
        if self._action_scale is not None:
            action = action * self._action_scale + self._action_offset
        obs, reward, success = self._step(action)
        self._steps_left -= 1
        return StepResult(obs, reward, success, self._steps_left == 0)

    def render(self, width: int, height: int, camera: int | str | None = None) -> np.ndarray:
        """uint8 (height, width, 3) off-screen frame of the current state. Cameras by index or
        name; None: DMC's camera 0 (2 for quadruped), Metaworld's "corner" (turned upright)."""
        camera_id = self._camera_id(self._default_camera if camera is None else camera)
        frame = self._render_scene(width, height, camera_id, segmentation=False)
        if camera_id in self._upside_down:
            frame = np.ascontiguousarray(frame[::-1, ::-1])
        return frame

    def segmentation(self, width: int, height: int,
                     camera: int | str | None = None) -> np.ndarray:
        """int32 (height, width, 2): per pixel of render()'s frame of the current state (with the
        motion cues set, as render() draws them), the MuJoCo object id and type it shows;
        (-1, -1) where nothing is drawn (the sky). From MuJoCo's segmentation render."""
        camera_id = self._camera_id(self._default_camera if camera is None else camera)
        ids = self._render_scene(width, height, camera_id, segmentation=True)
        if camera_id in self._upside_down:
            ids = np.ascontiguousarray(ids[::-1, ::-1])
        return ids

    def floor_geoms(self) -> np.ndarray:
        """The geom ids of the world's floor planes (those motion cues move and widen)."""
        return np.array([f.geom for f in self._floors], np.int64)

    def _render_scene(self, width: int, height: int, camera_id: int,
                      segmentation: bool) -> np.ndarray:
        key = (height, width, "segmentation") if segmentation else (height, width)
        renderer = self._renderers.get(key)
        if renderer is None:
            # mujoco.Renderer refuses sizes beyond the model's off-screen buffer; grow it.
            vis = self._model.vis.global_
            vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
            renderer = mujoco.Renderer(self._model, height, width)
            if segmentation:
                renderer.enable_segmentation_rendering()
            _open_renderers.add(renderer)
            _close_renderers_at_exit()
            self._renderers[key] = renderer
        renderer.update_scene(self._data, camera=camera_id)
        if self._cues is not None:
            self._add_motion_cues(renderer.scene, camera_id)
        return renderer.render()

    def set_motion_cues(self, cues: MotionCues | None) -> None:
        """What render() adds so that a clip shows motion wherever the agent is (`MotionCues`);
        None: the model's scene as it is. A renderer builds the floors' drawn sizes and the
        skybox into its GL context, so a change to either drops the cached renderers."""
        self._cues = cues
        reach = cues.ground_reach if cues is not None else None
        sky = cues.sky_rgb if cues is not None else None
        if self._draw_floors(reach) | self._paint_sky(sky):
            for renderer in self._renderers.values():
                renderer.close()
            self._renderers.clear()

    def _draw_floors(self, reach: float | None) -> bool:
        """Floors with a uniform grid drawn `reach` m either way around the subject (None: as
        modelled); whether a drawn size changed. MuJoCo draws a plane as squares of its third
        size, lit at their corners: at DMC's 0.2-0.5 m, a 100 m wide floor would double a
        CPU frame's render time, while squares of reach / 25 (2 m) look the same."""
        sizes = self._model.geom_size
        changed = False
        for f in self._floors:
            size = (np.array([reach, reach, reach / 25]) if reach is not None and f.uniform
                    else f.size)
            changed |= not np.array_equal(sizes[f.geom], size)
            sizes[f.geom] = size
        return changed

    def _paint_sky(self, rgb: tuple[float, float, float] | None) -> bool:
        """The skybox in one colour (None: its own texels); whether its texels changed."""
        m = self._model
        boxes = [i for i in range(m.ntex)
                 if m.tex_type[i] == mujoco.mjtTexture.mjTEXTURE_SKYBOX and m.tex_nchannel[i] == 3]
        if not boxes or rgb == self._sky_rgb:
            return False
        adr, n = int(m.tex_adr[boxes[0]]), int(m.tex_width[boxes[0]] * m.tex_height[boxes[0]] * 3)
        texels = m.tex_data[adr:adr + n].reshape(-1, 3)
        if self._sky is None:
            self._sky = texels.copy()
        if rgb is None:
            texels[:] = self._sky
        else:
            texels[:] = np.round(np.asarray(rgb) * 255).astype(np.uint8)
        self._sky_rgb = rgb
        return True

    def _focus(self, camera_id: int) -> np.ndarray | None:
        """The world point a camera follows (the centre of mass of the subtree it tracks or is
        attached to); None for the free camera and fixed world cameras, which never move."""
        m = self._model
        if camera_id < 0:
            return None
        mode, body = int(m.cam_mode[camera_id]), int(m.cam_bodyid[camera_id])
        if mode in (mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY,
                    mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODYCOM):
            body = int(m.cam_targetbodyid[camera_id])
        elif mode == mujoco.mjtCamLight.mjCAMLIGHT_FIXED and body == 0:
            return None
        return self._data.subtree_com[body]

    def _add_motion_cues(self, scene: mujoco.MjvScene, camera_id: int) -> None:
        cues = self._cues
        focus = self._focus(camera_id)
        if cues is None or focus is None:
            return
        if cues.ground_follows:
            # Each floor is moved under the camera's subject by a whole number of its texture's
            # periods, so its grid stays where it was in the world: the floor looks infinite.
            # Only along an axis where the floor is at least a period wide, so that the shifted
            # floor still reaches half a period either side of the subject: fish's 1 m tank
            # floor (2 m period) stays where it is, and so do the runners' 1.6-2 m wide tracks
            # across (they run along x) unless drawn wider (`ground_reach`). mjvGeom's size is
            # not what a plane is drawn at: the model's, when the renderer was made, is.
            floors = {f.geom: f for f in self._floors}
            for g in scene.geoms[:scene.ngeom]:
                if g.objtype != mujoco.mjtObj.mjOBJ_GEOM or g.objid not in floors:
                    continue
                f = floors[g.objid]
                shift = np.round((focus[:2] - f.center) / f.period) * f.period
                g.pos[:2] += np.where(2 * self._model.geom_size[f.geom, :2] >= f.period, shift, 0.0)
        if cues.marker_row is not None:
            _add_distance_markers(scene, float(focus[0]), cues)
        if cues.camera_distance is not None:
            for cam in scene.camera:  # both eyes of MuJoCo's stereo pair
                pos, forward = np.array(cam.pos), np.array(cam.forward)
                along = float(np.dot(focus - pos, forward))
                cam.pos[:] = pos + (along - cues.camera_distance) * forward

    def set_render_quality(self, **quality: int) -> None:
        """Sets fields of the model's `vis.quality` (shadowsize, offsamples, numslices, ...)
        for render(). A renderer reads them once, when it makes its GL context, so the cached
        renderers are dropped when a value changes."""
        current = self._model.vis.quality
        changed = {k: v for k, v in quality.items() if getattr(current, k) != v}
        for name, value in changed.items():
            setattr(current, name, value)
        if changed:
            for renderer in self._renderers.values():
                renderer.close()
            self._renderers.clear()

    def set_reflections(self, on: bool) -> None:
        """Mirror images in reflective floors (DMC's grid) in render(), or not. Off, a 256 px
        frame renders about a third faster on a CPU; only the floor's mirror image is lost."""
        if self._reflectance is None:
            self._reflectance = self._model.mat_reflectance.copy()
        self._model.mat_reflectance[:] = self._reflectance if on else 0.0

    def _camera_id(self, camera: int | str) -> int:
        names = [self._model.camera(i).name for i in range(self._model.ncam)]
        if isinstance(camera, str):
            if camera in names:
                return names.index(camera)
        elif -1 <= camera < self._model.ncam:  # -1: MuJoCo's free camera
            return int(camera)
        raise ValueError(f"{self.task}: no camera {camera!r}; cameras: -1 (free), "
                         + ", ".join(f"{i} {n!r}" for i, n in enumerate(names)))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()
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

"""Off-screen frames of an env's MuJoCo model, and what they draw to show motion.

An env (`trainer.envs.Env`) renders through its `Scene`: cameras by index or name (Metaworld's
upside-down corner cameras turned upright), MuJoCo's segmentation render, and the motion cues a
clip draws so that speed and direction show wherever the agent is (`MotionCues`: floors that
follow the camera's subject, drawn to the horizon, a plain sky, distance posts, the camera's
distance). A renderer per frame size is kept until a change to what it built into its GL
context (the floors' drawn sizes, the skybox, `vis.quality`) drops them all.
"""

from __future__ import annotations

import atexit
import functools
import weakref
from dataclasses import dataclass

import mujoco
import numpy as np

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


class Scene:
    """Renders one env's model in its current state (`trainer.envs.Env` draws through it)."""

    def __init__(self, task: str, model: mujoco.MjModel, data: mujoco.MjData,
                 default_camera: int | str) -> None:
        self.task = task
        self._model, self._data = model, data
        self._default_camera = default_camera
        self._upside_down = _upside_down_cameras(model)
        self._renderers: dict[tuple[int, int] | tuple[int, int, str], mujoco.Renderer] = {}
        self._reflectance: np.ndarray | None = None  # the model's own, once reflections are set
        self._floors = _floor_planes(model)
        self._cues: MotionCues | None = None  # set_motion_cues()
        self._sky: np.ndarray | None = None  # the skybox's own texels, once painted
        self._sky_rgb: tuple[float, float, float] | None = None  # the colour painted, if any

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
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()

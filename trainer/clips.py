"""Off-screen clips of preference-query segments, as short h264 mp4 files that browsers play.

A segment is re-rendered from the physics states stored with its trajectory (`env.restore()`
then `env.render()` per step), so the clip shows exactly what the agent did, whatever the env
was doing before. Rendering moves the env's simulator (and on Metaworld a change of goal variant
re-runs the task's reset), so give clips an env of their own rather than the one being trained.

Files are encoded by imageio-ffmpeg's bundled ffmpeg (libx264, yuv420p, moov atom first so that
playback can start before the whole file has arrived), written under a temporary name in the
target folder and renamed into place, so a reader never sees a half-written clip.

Render quality: software rendering (Mesa's llvmpipe behind `MUJOCO_GL=egl` or `osmesa` on a
machine without a GPU) spends its time on the shadow pass and on the geometry's triangles.
At 128 px on 2 cores, MuJoCo's defaults (a 2048-4096 texel shadow map, 4x multisampling,
capsules of 28 x 16 facets) render cheetah at 25-45 fps; a 512-texel shadow map without
multisampling at 75-120 fps; and with 12 x 8 facets as well at 140-240 fps, with no difference
to see at 128-256 px (`benchmarks/bench_clips.py`). At 256 px the floor's mirror image costs a
third of the frame; clips leave it out (`reflections`). A renderer reads these settings once, when
it is created: `iter_segment_frames()` sets them on the env first, and the env drops renderers
made with other settings.

Clips are 256 x 256 by default; a run may choose another size (`runs.clip_size`, one of
`runvocab.clip_format.CLIP_SIZES`, 320 x 240 among them for the wide DMC scenes). They are
encoded at `CLIP_FPS` (100/3), one frame per environment step, so 50 steps play in 1.5 s as the
paper's labellers saw them; how that relates to a task's own time is
`runvocab.clip_format.real_time_ratio` (cheetah, 10 ms a step: a third of real speed). Walkers,
runners and swimmers are filmed by the camera that follows them (`CLIP_CAMERAS`), so the body
stays in frame however far it goes.

Motion cues (`ClipConfig.motion_cues`, on by default): a following camera alone shows no speed
and no direction once the body is past the end of the drawn floor (DMC's floors end 2 m behind
the start and 50-250 m ahead; cheetah's whole view is then the skybox, which moves with the
camera). Clips draw each floor moved under the body by whole periods of its grid, so the grid
stays fixed in the world and the ground is in every frame, and the planar runners (cheetah,
walker, hopper: `MARKER_ROWS`) get a row of posts behind the track, one a metre, yellow every
5 m, red at the start. `ground_fractions()` measures the ground in each frame; tests and
`benchmarks/bench_ground.py` check that no frame is without it.

The scene around the body: DMC's runners' tracks are 1.6-2 m wide, so a camera filming from the
side saw a thin strip of floor with the skybox's starfield above and below it. Clips draw their
floors `GROUND_REACH` m either way (ground from the bottom of the frame to the horizon), every
DMC sky plain (`SKY_RGB`), and put each runner's camera at a distance of its own
(`CAMERA_DISTANCES`), so that the standing body fills `BODY_SHARE` of the frame's height.
`frame_shares()` measures the body's height and the sky in the lowest quarter per frame.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rundata import clip_codec
from runvocab.clip_format import CLIP_FPS, CLIP_SIZES, DEFAULT_CLIP_SIZE, dmc_domain
from trainer.trajectories import Trajectory

if TYPE_CHECKING:  # not at run time: the worker builds a ClipConfig before MuJoCo's import
    from trainer.envs import Env
    from trainer.scene import MotionCues

MIN_SIZE, MAX_SIZE = 64, 512
DEFAULT_WIDTH, DEFAULT_HEIGHT = CLIP_SIZES[DEFAULT_CLIP_SIZE]
CLIP_CAMERAS: dict[str, str] = {
    "cheetah": "side",
    "walker": "side",
    "quadruped": "y",
    "hopper": "cam0",
    "humanoid": "side",
    "humanoid_CMU": "side",
    "dog": "y-axis",
    "fish": "tracking_y",
    "swimmer": "tracking1",
}
"""per DMC domain, the camera a clip is filmed by: the one that tracks the body's centre of mass
from the side (quadruped's "y" keeps the whole body in view; "x" films it from behind), so a
runner never leaves the frame. Other domains, and Metaworld, keep their env's default view."""
MARKER_ROWS: dict[str, float] = {"cheetah": 0.7, "walker": 0.7, "hopper": 0.9}
"""per planar DMC runner, the y (m) of the row of distance posts: behind the body as its side
camera sees it, on the far half of the floor"""
CAMERA_DISTANCES: dict[str, float] = {"cheetah": 2.3, "walker": 3.1, "hopper": 2.45,
                                      "quadruped": 2.6}
"""per DMC domain, metres from the clip camera to the body it follows, along its line of sight:
the body standing as modelled fills `BODY_SHARE` of the frame's height, or less where its length
would then fill more than `BODY_WIDTH_SHARE` of a square frame's width (cheetah, quadruped). The
model's own: cheetah 3, walker 2, hopper 2.8, quadruped 4.5 (`tests/trainer/test_clip_scene.py`
measures the shares; `benchmarks/bench_ground.py` over many clips)"""
BODY_SHARE = 0.6
"""the share of the frame's height the standing body fills (`CAMERA_DISTANCES`)"""
BODY_WIDTH_SHARE = 0.75
"""the most of a square frame's width a standing body's length may take (`CAMERA_DISTANCES`)"""
GROUND_REACH = 50.0
"""metres the planar runners' floors are drawn either side of the body, across their 1.6-2 m
wide tracks as along them: ground from the bottom of a side-filmed frame to the horizon"""
SKY_RGB = (0.6, 0.75, 0.9)
"""the plain sky of DMC clips, in place of the skybox's starfield"""
METAWORLD_ARM = "right_arm_base_link"
"""the body at the root of Metaworld's Sawyer arm: what its clips film (`subject_geoms`)"""
GROUND_MIN_FRACTION = 0.01
"""a frame with less than this share of its pixels on a floor counts as one without ground"""


@dataclass(frozen=True)
class ClipConfig:
    """How segments are rendered and encoded."""

    width: int = DEFAULT_WIDTH
    """frame width in pixels: even, 64 to 512"""
    height: int = DEFAULT_HEIGHT
    """frame height in pixels: even, 64 to 512"""
    fps: float = CLIP_FPS
    """playback rate, one frame per step: at 100/3, a 50-step segment lasts 1.5 s"""
    camera: int | str | None = None
    """camera index or name; None: the task's clip camera (`clip_camera`)"""
    shadow_size: int | None = 512
    """shadow-map side in texels (0: no shadows; None: the model's own, 2048 or 4096)"""
    multisamples: int | None = 0
    """off-screen multisampling samples (None: the model's own, 4)"""
    slices: int | None = 12
    """facets around built-in spheres, capsules and cylinders (None: the model's own, 28)"""
    stacks: int | None = 8
    """facets along built-in spheres and capsules (None: the model's own, 16)"""
    motion_cues: bool = True
    """the floor drawn under the body wherever it is, and distance posts beside planar runners'
    track (`motion_cues()`); off: the model's scene as it is"""
    reflections: bool = False
    """mirror images in reflective floors; off, a 256 px cheetah pair renders about 30% faster
    on a CPU, and only the floor's mirror image is lost"""
    crf: int = 23
    """x264 constant rate factor: 0 is lossless, 51 the worst; 23 is x264's default"""
    preset: str = "veryfast"
    """x264 speed preset; at these sizes "veryfast" encodes faster than "medium" and no larger"""
    pixel_format: str = "yuv420p"
    """chroma layout; yuv420p is the one every browser decodes"""
    macro_block_size: int = 2
    """width and height must be multiples of this (imageio would otherwise rescale frames);
    2 is what yuv420p needs, 16 suits old hardware decoders"""

    def __post_init__(self) -> None:
        if not (isinstance(self.macro_block_size, int) and self.macro_block_size >= 1):
            raise ValueError(f"ClipConfig: macro_block_size must be a positive integer, "
                             f"got {self.macro_block_size!r}")
        step = math.lcm(2, self.macro_block_size)  # yuv420p halves the chroma planes: even sizes
        for name in ("width", "height"):
            size = getattr(self, name)
            if not (isinstance(size, int) and MIN_SIZE <= size <= MAX_SIZE and size % step == 0):
                raise ValueError(f"ClipConfig: {name} must be a multiple of {step} pixels in "
                                 f"[{MIN_SIZE}, {MAX_SIZE}], got {size!r}")
        if not self.fps > 0:
            raise ValueError(f"ClipConfig: fps must be positive, got {self.fps!r}")
        for name, low in (("shadow_size", 0), ("multisamples", 0), ("slices", 3), ("stacks", 2)):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= low):
                raise ValueError(f"ClipConfig: {name} must be an integer >= {low} or None, "
                                 f"got {value!r}")
        if not 0 <= self.crf <= 51:
            raise ValueError(f"ClipConfig: crf must be in [0, 51], got {self.crf}")


def render_quality(cfg: ClipConfig) -> dict[str, int]:
    """The config's settings as MuJoCo `model.vis.quality` fields (those not left as None)."""
    fields = {"shadowsize": cfg.shadow_size, "offsamples": cfg.multisamples,
              "numslices": cfg.slices, "numstacks": cfg.stacks}
    return {k: v for k, v in fields.items() if v is not None}


def clip_camera(task: str) -> str | None:
    """The camera a task's clips are filmed by (`CLIP_CAMERAS`); None: the env's default."""
    family, _, name = task.partition(":")
    return CLIP_CAMERAS.get(dmc_domain(name)) if family == "dmc" else None


def motion_cues(task: str) -> MotionCues | None:
    """What a task's clips draw to show motion (`trainer.scene.MotionCues`): on DMC, the floor
    that follows the camera under a plain sky, the camera at its task's distance
    (`CAMERA_DISTANCES`) and, for planar runners (`MARKER_ROWS`), distance posts and the floor
    drawn to the horizon; None on Metaworld, whose cameras are fixed."""
    family, _, name = task.partition(":")
    if family != "dmc":
        return None
    from trainer.scene import MotionCues  # here: the worker imports this module before MuJoCo

    domain = dmc_domain(name)
    runner = domain in MARKER_ROWS
    return MotionCues(marker_row=MARKER_ROWS.get(domain),
                      ground_reach=GROUND_REACH if runner else None, sky_rgb=SKY_RGB,
                      camera_distance=CAMERA_DISTANCES.get(domain))


def sized(cfg: ClipConfig, clip_size: str | None) -> ClipConfig:
    """`cfg` at a run's clip size (a `CLIP_SIZES` name; None keeps cfg's own)."""
    if clip_size is None:
        return cfg
    width, height = CLIP_SIZES[clip_size]
    return dataclasses.replace(cfg, width=width, height=height)


def iter_segment_frames(env: Env, traj_states: np.ndarray, context: int, start: int,
                        length: int, cfg: ClipConfig) -> Iterator[np.ndarray]:
    """Frames of steps start .. start+length-1, one at a time (uint8 (h, w, 3) each)."""
    states = np.asarray(traj_states)
    if states.ndim != 2 or length < 1 or start < 0 or start + length > len(states):
        raise ValueError(f"{env.task}: segment [{start}, {start + length}) does not fit in "
                         f"{len(states)} stored states of shape {states.shape}")
    # Before the first render: a renderer takes these settings when it is created.
    env.set_render_quality(**render_quality(cfg))
    env.set_reflections(cfg.reflections)
    env.set_motion_cues(motion_cues(env.task) if cfg.motion_cues else None)
    camera = cfg.camera if cfg.camera is not None else clip_camera(env.task)

    def frames() -> Iterator[np.ndarray]:
        for state in states[start:start + length]:
            env.restore(state, context)
            yield env.render(cfg.width, cfg.height, camera)

    return frames()  # checked above now, rendered lazily


def render_segment(env: Env, traj_states: np.ndarray, context: int, start: int, length: int,
                   cfg: ClipConfig) -> np.ndarray:
    """uint8 (length, height, width, 3): the segment re-rendered from its stored states."""
    frames = np.empty((length, cfg.height, cfg.width, 3), np.uint8)
    for i, frame in enumerate(iter_segment_frames(env, traj_states, context, start, length, cfg)):
        frames[i] = frame
    return frames


def ground_fractions(env: Env, traj_states: np.ndarray, context: int, start: int, length: int,
                     cfg: ClipConfig) -> np.ndarray:
    """float (length,): per frame of the clip `iter_segment_frames` renders, the share of its
    pixels that show a floor (MuJoCo's segmentation render of the same scene, motion cues
    included). Below `GROUND_MIN_FRACTION`, a frame has no ground to see motion against."""
    return frame_shares(env, traj_states, context, start, length, cfg)["ground"]


def frame_shares(env: Env, traj_states: np.ndarray, context: int, start: int, length: int,
                 cfg: ClipConfig) -> dict[str, np.ndarray]:
    """Per frame of the clip `iter_segment_frames` renders, from MuJoCo's segmentation render of
    the same scene (motion cues included), float (length,) arrays:

    - "ground": the share of its pixels that show a floor;
    - "sky_below": the share of its lowest quarter that shows the sky (nothing drawn);
    - "body_height", "body_width": the height and width of the body's bounding box as shares
      of the frame's (`subject_geoms`; 0 where the body is out of the frame)."""
    # Sets the env up exactly as for the clip (and checks the segment).
    iter_segment_frames(env, traj_states, context, start, length, cfg)
    camera = cfg.camera if cfg.camera is not None else clip_camera(env.task)
    import mujoco  # here: the worker imports this module before MuJoCo

    floors, body = env.floor_geoms(), subject_geoms(env)
    out = {k: np.empty(length) for k in ("ground", "sky_below", "body_height", "body_width")}
    for i, state in enumerate(np.asarray(traj_states)[start:start + length]):
        env.restore(state, context)
        ids = env.segmentation(cfg.width, cfg.height, camera)
        geoms = np.where(ids[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, ids[..., 0], -1)
        out["ground"][i] = np.isin(geoms, floors).mean()
        out["sky_below"][i] = (ids[-(cfg.height // 4):, :, 1] < 0).mean()
        shown = np.isin(geoms, body)
        rows, cols = np.flatnonzero(shown.any(axis=1)), np.flatnonzero(shown.any(axis=0))
        out["body_height"][i] = (rows[-1] - rows[0] + 1) / cfg.height if len(rows) else 0.0
        out["body_width"][i] = (cols[-1] - cols[0] + 1) / cfg.width if len(cols) else 0.0
    return out


def subject_geoms(env: Env) -> np.ndarray:
    """The geoms of what a task's clips film: on DMC every body but the world's (the agent), on
    Metaworld the arm (`METAWORLD_ARM` and the bodies below it), not the table or the objects."""
    model = env._model  # read only
    if env.task.startswith("metaworld:"):
        arm = {model.body(METAWORLD_ARM).id}
        for b in range(model.nbody):  # parents come before their children
            if model.body_parentid[b] in arm:
                arm.add(b)
        bodies = np.array(sorted(arm))
    else:
        bodies = np.arange(1, model.nbody)
    return np.flatnonzero(np.isin(model.geom_bodyid, bodies))


def moved_states(env: Env, traj_states: np.ndarray, dx: float, dy: float = 0.0) -> np.ndarray:
    """The stored DMC states with the body moved dx m along x (and dy along y where it has a
    free joint): the same motion further along the run, as a long-running agent would be. DMC's
    floors collide as infinite planes, so the physics is the same there."""
    import mujoco

    model = env._model  # the joint layout, read only
    states = np.array(traj_states, np.float64, copy=True)
    for j in range(model.njnt):
        if model.jnt_bodyid[j] == 0 or model.body_parentid[model.jnt_bodyid[j]] != 0:
            continue  # only the root joints of bodies hanging off the world
        adr = int(model.jnt_qposadr[j])
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            states[:, adr] += dx
            states[:, adr + 1] += dy
        elif (model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE
              and np.allclose(model.jnt_axis[j], [1, 0, 0])):
            states[:, adr] += dx
    return states


def encode_mp4(frames: Iterable[np.ndarray], path: str | os.PathLike, cfg: ClipConfig) -> Path:
    """Writes the frames (uint8 (height, width, 3) each, an array or any iterable: frames are
    encoded as they come) to an h264 mp4 at `path`, atomically, with `cfg`'s encoder settings
    (`rundata.clip_codec.encode_mp4`, which external clients' frames go through too)."""
    return clip_codec.encode_mp4(frames, path, fps=cfg.fps, width=cfg.width, height=cfg.height,
                                 crf=cfg.crf, preset=cfg.preset, pixel_format=cfg.pixel_format,
                                 macro_block_size=cfg.macro_block_size)


def render_query_clips(env: Env, traj0: Trajectory, start0: int, traj1: Trajectory, start1: int,
                       length: int, out_dir: str | os.PathLike, stem: str,
                       cfg: ClipConfig) -> tuple[str, str]:
    """Renders and encodes both segments of a query to `out_dir/<stem>-0.mp4` and
    `<stem>-1.mp4`; returns those two file names, relative to out_dir."""
    if not stem or Path(stem).name != stem or stem.startswith("."):
        raise ValueError(f"stem must be a plain file name, got {stem!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    # Both segments are checked before either file is written.
    sides = [iter_segment_frames(env, traj.states, traj.context, start, length, cfg)
             for traj, start in ((traj0, start0), (traj1, start1))]
    names = (f"{stem}-0.mp4", f"{stem}-1.mp4")
    for name, frames in zip(names, sides, strict=True):
        encode_mp4(frames, out / name, cfg)  # streamed: ffmpeg encodes while the next renders
    return names

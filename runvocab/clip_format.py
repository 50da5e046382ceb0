"""How a run's clips look and how fast they play: the sizes a run may choose, the frame rate
clips are encoded at, and how long one environment step lasts in each task's simulated time.
The worker renders with these; the server offers the sizes and tells the label page how clip
time relates to the task's own time. Data only: no torch, no MuJoCo.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

CLIP_SIZES: dict[str, tuple[int, int]] = {
    "256x256": (256, 256),
    "320x240": (320, 240),
    "128x128": (128, 128),
}
"""a run's `clip_size` choices, name -> (width, height) in pixels: square, the widescreen one
for the wide DMC scenes, and the small fast one"""
DEFAULT_CLIP_SIZE = "256x256"

CLIP_FPS = 100 / 3
"""frames per second of every clip, one frame per environment step: 50 steps play in 1.5 s, as
the paper's labellers saw them"""

# Simulated seconds per environment step (dm_control's control timestep; Metaworld's frame skip
# times its physics timestep). tests/trainer/test_clips.py checks them against the installed
# suites.
_DMC_STEP_S: dict[str, float] = {
    "acrobot": 0.01,
    "ball_in_cup": 0.02,
    "cartpole": 0.01,
    "cheetah": 0.01,
    "dog": 0.015,
    "finger": 0.02,
    "fish": 0.04,
    "hopper": 0.02,
    "humanoid": 0.025,
    "humanoid_CMU": 0.02,
    "lqr": 0.03,
    "manipulator": 0.01,
    "pendulum": 0.02,
    "point_mass": 0.02,
    "quadruped": 0.02,
    "reacher": 0.02,
    "stacker": 0.01,
    "swimmer": 0.03,
    "walker": 0.025,
}
METAWORLD_STEP_S = 0.0125
"""5 physics steps of 2.5 ms"""


def parse_clip_size(name: str) -> tuple[int, int]:
    """(width, height) of a clip size name; ValueError listing the valid names."""
    if name not in CLIP_SIZES:
        raise ValueError(f"unknown clip size {name!r}; valid: {', '.join(CLIP_SIZES)}")
    return CLIP_SIZES[name]


def dmc_domain(name: str) -> str:
    """The dm_control domain of a task name without its family ("ball_in_cup_catch" ->
    "ball_in_cup"): the longest known domain that prefixes it, else the part before "_"."""
    known = [d for d in _DMC_STEP_S if name == d or name.startswith(d + "_")]
    return max(known, key=len) if known else name.split("_", 1)[0]


def step_seconds(task: str) -> float | None:
    """Simulated seconds per environment step of `task`; None when not known."""
    family, _, name = task.partition(":")
    if family == "metaworld":
        return METAWORLD_STEP_S
    if family == "dmc":
        return _DMC_STEP_S.get(dmc_domain(name))
    return None


def real_time_ratio(task: str, fps: float = CLIP_FPS) -> float | None:
    """How fast a clip plays at 1x against the task's own time: 0.33 means a second of clip
    shows a third of a simulated second (slow motion); None when the step length is unknown."""
    seconds = step_seconds(task)
    return None if seconds is None else seconds * fps


@dataclass(frozen=True)
class ClipInfo:
    """What a decoded clip holds."""

    container: str
    """mp4 or webm"""
    codec: str
    width: int
    height: int
    frames: int
    seconds: float

    def as_json(self) -> dict[str, Any]:
        return {"container": self.container, "codec": self.codec, "width": self.width,
                "height": self.height, "frames": self.frames, "seconds": self.seconds}

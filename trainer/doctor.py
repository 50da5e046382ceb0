"""`sepoa doctor`: can this machine render MuJoCo off-screen, how fast, and is the picture upright?

Off-screen rendering is where RL set-ups most often break: no EGL vendor library, an EGL without
a device platform, no libOSMesa, a driver that renders black or crashes. MuJoCo and dm_control
choose their GL backend once, at import, from `MUJOCO_GL` (OSMesa also wants
`PYOPENGL_PLATFORM=osmesa`), and a broken driver can crash the process that loads it, so each
probe runs in a fresh Python process with both variables set (`python -m trainer.doctor`).

A probe renders one task at a fixed state (seed 0, just reset, `ClipConfig()`'s render quality),
reads the GL vendor, renderer and version in the rendering context, times a burst of frames, and
compares the first frame with a stored 16 x 16 grey thumbnail of the same view (`REFERENCES`).
Measured with EGL and OSMesa (Mesa llvmpipe): upright frames correlate with their thumbnail at
0.97 or more (seeds 0 to 5, 64 or 128 px, the model's or the clips' render quality); the same
frames flipped vertically, or turned by 180 degrees as MuJoCo renders Metaworld's corner camera
before `Env.render` turns it upright, at 0.1 or less.

`choose_backend()` is the worker's start check: one frame of DMC under the requested backend
(`MUJOCO_GL`, EGL by default), else under the other one, whose variables it then sets for the
worker's own process, before that imports MuJoCo.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

BACKENDS = ("egl", "osmesa")
TASKS = ("dmc:cheetah_run", "metaworld:door-open")
CHECK_TASK = TASKS[0]
"""the worker's start check renders this one"""
PACKAGES = {"egl": "libegl1 libegl-mesa0 libgl1-mesa-dri", "osmesa": "libosmesa6"}
INSTALL_HINT = (f"install EGL (apt-get install {PACKAGES['egl']}, or a GPU driver's EGL) or "
                f"OSMesa (apt-get install {PACKAGES['osmesa']})")
MATCH = 0.8
"""a thumbnail correlation of at least this is a match"""
THUMB = 16
_RESULT = "sepoa-doctor-probe: "
"""the prefix of the probe process's result line on its stdout"""

# 16 x 16 grey thumbnails of each probe's first frame (128 px, seed 0, just reset, the clips'
# render quality), one hex digit a cell, the contrast stretched to 0-f (`thumbnail_rows()`).
REFERENCES: dict[str, tuple[str, ...]] = {
    "dmc:cheetah_run": (
        "bccccbccccccbcbb", "bbbbbbbbbbbbbbbb", "aaaaaabbbbbbbbaa", "aaaaaaaaaaaaaaaa",
        "a99aa9a999999999", "9999999999999998", "888888888888b888", "7777aeedccbfb888",
        "77778e99aaea7777", "67767f8666d67666", "6667e66666b86666", "23219122454a3200",
        "0234755642241001", "3334544433333322", "4443434334434334", "3333333333333333",
    ),
    "metaworld:door-open": (
        "aaaaaaaaa989aaaa", "aaaaaaaaa657aaaa", "aaaaaaaa7525aaaa", "aaaaaaa93416aaaa",
        "aaaaaaaa4337aaaa", "aaaaa987423569aa", "aaa7212215626577", "aaa711125a642664",
        "a986111138665254", "6655223367777752", "5566666677778982", "7766666777667651",
        "6775555655658641", "556766656667ae22", "b755655669b8b801", "af845557cc324c01",
    ),
}


# ---------------------------------------------------------------------------------------------
# Is the frame upright?

def thumbnail(frame: np.ndarray) -> np.ndarray:
    """(16, 16) float: the mean grey level of each cell of an (h, w, 3) frame."""
    grey = np.asarray(frame, np.float64).mean(axis=2)
    h, w = grey.shape
    rows, cols = (np.arange(THUMB) * h) // THUMB, (np.arange(THUMB) * w) // THUMB
    sums = np.add.reduceat(np.add.reduceat(grey, rows, axis=0), cols, axis=1)
    return sums / np.outer(np.diff(rows, append=h), np.diff(cols, append=w))


def thumbnail_rows(frame: np.ndarray) -> tuple[str, ...]:
    """The thumbnail as `REFERENCES` stores it."""
    thumb = thumbnail(frame)
    span = max(float(np.ptp(thumb)), 1e-9)
    levels = np.rint((thumb - thumb.min()) / span * 15).astype(int)
    return tuple("".join(f"{v:x}" for v in row) for row in levels)


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


@dataclass(frozen=True)
class Orientation:
    verdict: str
    """upright | upside down | turned 180 | blank | unclear | no reference"""
    r: float = math.nan
    """the frame's correlation with the task's thumbnail"""
    r_flipped: float = math.nan
    """the best correlation of the frame flipped vertically or turned by 180 degrees"""

    def describe(self) -> str:
        if self.verdict == "upright":
            return f"yes (r {self.r:.2f}; flipped {self.r_flipped:.2f})"
        if self.verdict in ("upside down", "turned 180"):
            return f"NO: {self.verdict} (r {self.r:.2f}; flipped {self.r_flipped:.2f})"
        if self.verdict == "unclear":
            return f"unclear (r {self.r:.2f}; flipped {self.r_flipped:.2f})"
        return self.verdict


def orientation(frame: np.ndarray, task: str) -> Orientation:
    """Compares a probe's first frame of `task` with its stored thumbnail, upright and flipped."""
    if task not in REFERENCES:
        return Orientation("no reference")
    thumb = thumbnail(frame)
    if thumb.std() < 0.5:
        return Orientation("blank")
    reference = np.array([[int(c, 16) for c in row] for row in REFERENCES[task]], np.float64)
    # The view that would make the frame match: the frame as it is, flipped, or turned.
    scores = {"upright": thumb, "upside down": thumb[::-1], "turned 180": thumb[::-1, ::-1]}
    r = {name: _correlation(view, reference) for name, view in scores.items()}
    best = max(r, key=lambda name: r[name])
    return Orientation(best if r[best] >= MATCH else "unclear", r["upright"],
                       max(r["upside down"], r["turned 180"]))


# ---------------------------------------------------------------------------------------------
# Probes, each in a fresh process

@dataclass(frozen=True)
class Probe:
    """What one backend did with one task."""

    backend: str
    task: str
    error: str | None = None
    """None: it rendered a frame; else why not, in one line"""
    vendor: str = ""
    renderer: str = ""
    version: str = ""
    """GL_VENDOR, GL_RENDERER and GL_VERSION, read in the rendering context"""
    first_frame_s: float = math.nan
    """from the probe's start to its first frame: imports, the model, the GL context"""
    fps: float = math.nan
    """frames per second over the burst after the first frame"""
    upright: str = ""
    """the `Orientation` verdict"""
    r: float = math.nan
    r_flipped: float = math.nan

    @property
    def works(self) -> bool:
        return self.error is None

    @property
    def flipped(self) -> bool:
        return self.upright in ("upside down", "turned 180")

    def orientation(self) -> Orientation:
        return Orientation(self.upright, self.r, self.r_flipped)


def backend_environment(backend: str) -> dict[str, str]:
    """The variables that select `backend` for MuJoCo, dm_control and PyOpenGL."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown rendering backend {backend!r}; valid: {', '.join(BACKENDS)}")
    return {"MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}


def probe(backend: str, task: str, *, size: int = 128, frames: int = 20,
          timeout: float = 180.0) -> Probe:
    """Render `task` under `backend` in a fresh process (this process's environment otherwise)."""
    command = [sys.executable, "-m", "trainer.doctor", task, str(size), str(frames)]
    env = os.environ | backend_environment(backend)
    try:
        done = subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        return Probe(backend, task, error=f"no frame within {timeout:g} s (the driver hangs)")
    for line in reversed(done.stdout.splitlines()):
        if line.startswith(_RESULT):
            return Probe(backend, task, **json.loads(line.removeprefix(_RESULT)))
    return Probe(backend, task, error=_died(done))


def _died(done: subprocess.CompletedProcess[str]) -> str:
    """One line for a probe process that ended without a result."""
    lines = [line.strip() for line in done.stderr.splitlines() if line.strip()]
    last = f": {lines[-1]}" if lines else ""
    if done.returncode < 0:
        try:
            name = signal.Signals(-done.returncode).name
        except ValueError:
            name = f"signal {-done.returncode}"
        return f"the process crashed ({name}){last}"
    return f"the process exited with status {done.returncode}{last}"


def _probe_here(task: str, size: int, frames: int) -> dict[str, Any]:
    """The probe process's work; MUJOCO_GL and PYOPENGL_PLATFORM are set by its parent."""
    start = time.perf_counter()
    from trainer.clips import ClipConfig, render_quality
    from trainer.envs import make_env

    env = make_env(task, 0, episode_length=2)
    try:
        env.reset()
        env.set_render_quality(**render_quality(ClipConfig()))
        frame = env.render(size, size)
        first = time.perf_counter() - start
        from OpenGL import GL  # type: ignore[import-untyped]

        # Read in the renderer's GL context, which render() left current.
        vendor, renderer, version = (
            (GL.glGetString(name) or b"?").decode(errors="replace")
            for name in (GL.GL_VENDOR, GL.GL_RENDERER, GL.GL_VERSION))
        burst = time.perf_counter()
        for _ in range(frames):
            env.render(size, size)
        fps = frames / (time.perf_counter() - burst) if frames else math.nan
    finally:
        env.close()
    seen = orientation(frame, task)
    error = "the frame is blank (one colour): the driver renders nothing" \
        if seen.verdict == "blank" else None
    return {"error": error, "vendor": vendor, "renderer": renderer, "version": version,
            "first_frame_s": first, "fps": fps, "upright": seen.verdict, "r": seen.r,
            "r_flipped": seen.r_flipped}


def _probe_process(argv: Sequence[str]) -> int:
    task, size, frames = argv[0], int(argv[1]), int(argv[2])
    try:
        result = _probe_here(task, size, frames)
    except Exception as err:  # noqa: BLE001 - any failure is the probe's answer
        text = str(err).strip().splitlines()
        result = {"error": f"{type(err).__name__}: {text[0] if text else ''}".rstrip(": ")}
    print(_RESULT + json.dumps(result), flush=True)
    return 0


# ---------------------------------------------------------------------------------------------
# `sepoa doctor` and the worker's start check

def table(probes: Sequence[Probe]) -> str:
    header = ("backend", "task", "renders", "first frame", "fps", "upright",
              "GL vendor | renderer | version (or the error)")
    rows = [header]
    for p in probes:
        if p.works:
            rows.append((p.backend, p.task, "yes", f"{p.first_frame_s:.1f} s",
                         "-" if math.isnan(p.fps) else f"{p.fps:.0f}",
                         p.orientation().describe(), f"{p.vendor} | {p.renderer} | {p.version}"))
        else:
            error = str(p.error) if len(str(p.error)) <= 200 else f"{str(p.error)[:199]}…"
            rows.append((p.backend, p.task, "NO", "-", "-", "-", f"error: {error}"))
    widths = [max(len(row[i]) for row in rows) for i in range(len(header) - 1)]
    return "\n".join("  ".join([*(c.ljust(w) for c, w in zip(row, widths, strict=False)),
                                row[-1]]) for row in rows)


def requested_backend() -> str:
    return os.environ.get("MUJOCO_GL", "").strip().lower() or "egl"


def _order(requested: str) -> list[str]:
    """The backends in the order the worker tries them."""
    return [requested] + [b for b in BACKENDS if b != requested]


def run_doctor(backends: Sequence[str] = BACKENDS, tasks: Sequence[str] = TASKS, *,
               size: int = 128, frames: int = 20,
               echo: Callable[[str], None] = print) -> int:
    """Probe every backend with every task, print the table and a verdict; the exit status: 0
    when a backend renders every task whose suite loads here (upright where a thumbnail tells),
    2 for an unknown task, else 1."""
    probes = []
    for backend in backends:
        for task in tasks:
            print(f"rendering {task} with {backend} ...", file=sys.stderr, flush=True)
            probes.append(probe(backend, task, size=size, frames=frames))
    unknown = next((p.error for p in probes
                    if p.error and p.error.startswith("UnknownTaskError: ")), None)
    if unknown:
        print(f"error: {unknown.removeprefix('UnknownTaskError: ').split('; ')[0]} "
              "(`sepoa tasks` lists the valid names)", file=sys.stderr)
        return 2
    echo(table(probes))
    # A task whose suite is not installed fails under every backend alike: that says nothing
    # of rendering, so the verdict is on the other tasks (a host with only DMC, say).
    missing = {p.task: p.error for p in probes if _not_installed(p.error)
               and all(_not_installed(q.error) for q in probes if q.task == p.task)}
    tasks = [t for t in tasks if t not in missing]
    for task, error in missing.items():
        echo(f"not checked: {task}, whose suite does not load here ({error})")
    if not tasks:
        echo("error: no task loads here, so no backend could be checked; install the project's "
             "packages (pip install -e .)")
        return 1
    probes = [p for p in probes if p.task in tasks]
    renders = [b for b in backends if all(p.works for p in probes if p.backend == b)]
    usable = [b for b in renders if not any(p.flipped for p in probes if p.backend == b)]
    if usable:
        requested = requested_backend()
        worker = ""
        if requested in BACKENDS and set(BACKENDS) <= set(backends):
            chosen = next(b for b in _order(requested) if b in usable)
            worker = f"; a worker with MUJOCO_GL={requested} uses {chosen}"
        echo(f"ok: {' and '.join(usable)} render{'s' if len(usable) == 1 else ''} "
             f"{', '.join(tasks)} upright{worker}")
        return 0
    if renders:
        flipped = sorted({f"{p.task} under {p.backend}" for p in probes if p.flipped})
        echo(f"error: frames come out upside down ({'; '.join(flipped)}): clips would show them "
             "so; this is a rendering bug in trainer/scene.py, not a missing package")
        return 1
    which = (f"neither {' nor '.join(backends)} renders" if len(backends) > 1 else
             f"{backends[0]} does not render")
    echo(f"error: {which} {', '.join(tasks)}; {INSTALL_HINT}")
    return 1


def _not_installed(error: str | None) -> bool:
    return error is not None and error.startswith("ModuleNotFoundError: ")


class RenderingUnavailable(RuntimeError):
    """No off-screen backend works here; the message names what to install."""


def choose_backend(echo: Callable[[str], None], *, timeout: float = 180.0) -> str:
    """The worker's start check (see the module's docstring); returns the backend in use. The
    requested one when it renders, else the other, whose variables are then set in this
    process's environment. Must run before this process imports MuJoCo."""
    requested = requested_backend()
    if requested not in BACKENDS:
        echo(f"rendering: MUJOCO_GL={requested}, not checked (the check knows "
             f"{' and '.join(BACKENDS)})")
        return requested
    if "mujoco" in sys.modules:
        raise RuntimeError("choose_backend() runs before MuJoCo is imported (it reads MUJOCO_GL "
                           "once, at import)")
    errors: dict[str, str] = {}
    for backend in _order(requested):
        result = probe(backend, CHECK_TASK, size=64, frames=0, timeout=timeout)
        if not result.works:
            errors[backend] = str(result.error)
            continue
        os.environ.update(backend_environment(backend))
        seen = (f"{result.renderer}; frames upright" if result.upright == "upright" else
                f"{result.renderer}; WARNING frames {result.orientation().describe()}, "
                "sepoa doctor tells more")
        if backend == requested:
            echo(f"rendering: {backend} works ({seen})")
        else:
            echo(f"rendering: {requested} fails ({errors[requested]}); falling back to "
                 f"{backend} (MUJOCO_GL={backend}, PYOPENGL_PLATFORM={backend}; {seen})")
        return backend
    raise RenderingUnavailable(
        "no off-screen rendering: " + "; ".join(f"{b}: {e}" for b, e in errors.items())
        + f"; {INSTALL_HINT}")


if __name__ == "__main__":
    sys.exit(_probe_process(sys.argv[1:]))

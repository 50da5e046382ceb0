"""`sepoa doctor` and the worker's start check: the upright check tells flipped frames from
upright ones, a broken EGL is reported and the worker falls back to OSMesa and still renders
real clips, and with no backend at all both say what to install.

EGL is broken the way a machine without an EGL vendor library is: glvnd is pointed at a vendor
file that does not exist. OSMesa too is broken by naming a Gallium driver that does not exist
(Mesa's llvmpipe then crashes the process that asks it for a context)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from sqlalchemy import select
from worker_helpers import database, wait_for

from labelqueue import Query, create_run
from trainer import doctor
from trainer.doctor import Orientation, Probe, orientation
from trainer.envs import make_env

BROKEN_EGL = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent.json"}
BROKEN_OSMESA = {"GALLIUM_DRIVER": "nonexistent"}
DOCTOR = [sys.executable, "-m", "sepoa.cli", "doctor", "--task", "dmc:cheetah_run",
          "--frames", "3"]


def _run(command: list[str], extra: dict[str, str], timeout: float = 300) -> \
        subprocess.CompletedProcess[str]:
    env = os.environ | {"MUJOCO_GL": "egl"} | extra
    env.pop("PYOPENGL_PLATFORM", None)
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)


def _rows(stdout: str) -> dict[str, str]:
    """Each backend's table row, by backend."""
    return {line.split()[0]: line for line in stdout.splitlines()
            if line.split() and line.split()[0] in ("egl", "osmesa")}


@pytest.mark.parametrize("task", ["dmc:cheetah_run", "metaworld:door-open"])
def test_the_upright_check_tells_an_upright_frame_from_a_flipped_one(task: str) -> None:
    env = make_env(task, 3, episode_length=2)  # not the reference's seed
    env.reset()
    frame = env.render(64, 64)
    env.close()
    assert orientation(frame, task).verdict == "upright"
    assert orientation(frame[::-1], task).verdict == "upside down"
    # What MuJoCo renders through Metaworld's corner camera before Env.render turns it.
    assert orientation(frame[::-1, ::-1], task).verdict == "turned 180"
    assert orientation(np.zeros_like(frame), task).verdict == "blank"
    noise = np.random.default_rng(0).integers(0, 256, frame.shape, dtype=np.uint8)
    assert orientation(noise, task).verdict == "unclear"
    assert orientation(frame, "dmc:walker_walk") == Orientation("no reference")


def test_doctor_reports_each_backend_with_gl_strings_fps_and_orientation() -> None:
    done = _run(DOCTOR, {})
    assert done.returncode == 0, done.stdout + done.stderr
    rows = _rows(done.stdout)
    assert set(rows) == {"egl", "osmesa"}
    for row in rows.values():
        assert " yes " in row and "yes (r " in row  # renders, and upright
        vendor, renderer, version = row.split("  ")[-1].split(" | ")
        assert vendor.strip() and renderer and version[0].isdigit()  # "4.5 (Compat...) Mesa"
        fps = row.split()[5]
        assert float(fps) > 0
    assert done.stdout.splitlines()[-1].startswith("ok: egl and osmesa render")


def test_doctor_reports_a_broken_egl_and_passes_on_osmesa() -> None:
    done = _run(DOCTOR, BROKEN_EGL)
    assert done.returncode == 0, done.stdout + done.stderr
    rows = _rows(done.stdout)
    assert " NO " in rows["egl"] and "error: ImportError: " in rows["egl"]
    assert " yes " in rows["osmesa"] and "yes (r " in rows["osmesa"]
    assert "uses osmesa" in done.stdout.splitlines()[-1]


def test_with_no_backend_the_doctor_and_the_worker_say_what_to_install(tmp_path: Path) -> None:
    broken = BROKEN_EGL | BROKEN_OSMESA
    done = _run(DOCTOR, broken)
    assert done.returncode == 1
    assert " NO " in _rows(done.stdout)["osmesa"]  # here llvmpipe crashes: SIGSEGV
    last = done.stdout.splitlines()[-1]
    assert last.startswith("error: neither egl nor osmesa renders")
    assert "libegl1" in last and "libosmesa6" in last

    url = f"sqlite:///{tmp_path / 'queue.db'}"
    worker = _run([sys.executable, "-m", "sepoa", "worker", "--database-url", url,
                   "--data-dir", str(tmp_path), "--once"], broken)
    assert worker.returncode == 1
    [line] = worker.stderr.strip().splitlines()
    assert line.startswith("error: no off-screen rendering: egl: ImportError")
    assert "libegl1" in line and "libosmesa6" in line
    assert not (tmp_path / "queue.db").exists()  # it stopped before touching anything


@pytest.mark.slow
def test_a_worker_with_a_broken_egl_falls_back_to_osmesa_and_renders_clips(tmp_path: Path) -> None:
    url, sessions = database(tmp_path)
    with sessions() as session:
        run = create_run(session, name="people", teacher="human", task="dmc:cheetah_run",
                         algo="pebble", preset="tiny", seed=0, budget=2,
                         teacher_params={"eps": 0.0},
                         config={"steps": 400, "seed_steps": 100, "unsup_steps": 100,
                                 "episode_length": 50, "feedback.per_round": 2, "threads": 1})
    command = [sys.executable, "-m", "sepoa", "worker", "--database-url", url,
               "--data-dir", str(tmp_path / "data"), "--worker-id", "w1", "--once",
               "--poll-seconds", "0.1", "--clip-size", "64"]
    env = os.environ | {"MUJOCO_GL": "egl"} | BROKEN_EGL
    env.pop("PYOPENGL_PLATFORM", None)
    log = tmp_path / "worker.log"
    with open(log, "w") as out:
        worker = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)
        try:
            def clips() -> list[str]:
                with sessions() as session:
                    keys = session.scalars(select(Query.first_clip).where(
                        Query.run_id == run.id, Query.first_clip.is_not(None))).all()
                    session.commit()
                return [k for k in keys if k]

            keys = wait_for(clips, timeout=240, what="a clip")
        finally:
            worker.kill()
            worker.wait()
    text = log.read_text()
    assert ("[worker w1] rendering: egl fails (ImportError: Cannot initialize a headless EGL "
            "display.); falling back to osmesa (MUJOCO_GL=osmesa") in text, text
    frames = imageio.mimread(tmp_path / "data" / "clips" / keys[0])
    assert len(frames) == 20  # the tiny preset's segment length
    frame = np.asarray(frames[len(frames) // 2], np.float64)
    assert frame.shape == (64, 64, 3)
    # Upright: the clip's plain sky on top, its ground (tiled, lit) below. (The doctor's
    # thumbnails are of the probe's view, not of the clips' scene.)
    sky, ground = frame[:8].std(axis=(0, 1)).mean(), frame[-8:].std(axis=(0, 1)).mean()
    assert sky < ground, (sky, ground)


def test_a_task_whose_suite_is_not_installed_is_not_held_against_the_backend(
        monkeypatch: pytest.MonkeyPatch) -> None:
    def probe(backend: str, task: str, **_: object) -> Probe:
        if task.startswith("metaworld:"):
            return Probe(backend, task, error="ModuleNotFoundError: No module named 'metaworld'")
        if backend == "osmesa":
            return Probe(backend, task, error="ImportError: no libOSMesa")
        return Probe(backend, task, vendor="NVIDIA", renderer="H100", version="4.6",
                     first_frame_s=1.0, fps=2000.0, upright="yes", r=1.0, r_flipped=-0.5)

    monkeypatch.setattr(doctor, "probe", probe)
    lines: list[str] = []
    assert doctor.run_doctor(echo=lines.append) == 0
    assert lines[-2] == ("not checked: metaworld:door-open, whose suite does not load here "
                         "(ModuleNotFoundError: No module named 'metaworld')")
    assert lines[-1].startswith("ok: egl renders dmc:cheetah_run upright")

    def nothing_loads(backend: str, task: str, **_: object) -> Probe:
        return Probe(backend, task, error="ModuleNotFoundError: No module named 'mujoco'")

    monkeypatch.setattr(doctor, "probe", nothing_loads)
    lines.clear()
    assert doctor.run_doctor(echo=lines.append) == 1
    assert lines[-1].startswith("error: no task loads here")

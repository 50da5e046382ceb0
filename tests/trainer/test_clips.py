import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported; the project default

import ctypes.util
import re
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import imageio_ffmpeg
import numpy as np
import pytest

from runvocab.clip_format import CLIP_SIZES, METAWORLD_STEP_S, step_seconds
from trainer.clips import (
    CLIP_CAMERAS,
    ClipConfig,
    clip_camera,
    encode_mp4,
    iter_segment_frames,
    render_query_clips,
    render_segment,
    sized,
)
from trainer.envs import make_env
from trainer.trajectories import Trajectory

REPO = Path(__file__).resolve().parents[2]


def record(env, steps: int, seed: int = 0) -> Trajectory:
    """A random-action episode prefix, with the physics state of every step."""
    rng = np.random.default_rng(seed)
    env.reset()
    states = []
    for _ in range(steps):
        states.append(env.physics_state())
        env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
    return Trajectory(id=0, obs=np.zeros((steps, env.obs_dim), np.float32),
                      actions=np.zeros((steps, env.action_dim), np.float32),
                      true_rewards=np.zeros(steps, np.float32), states=np.array(states),
                      context=env.episode_context(), success=False)


def probe(path: Path) -> dict:
    """What ffmpeg itself says about the file's video stream."""
    err = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-hide_banner", "-i", str(path)],
                         capture_output=True, text=True).stderr
    video = re.search(r"Stream #\S+.*Video: (\w+).*?, (\w+)\(.*?, (\d+)x(\d+)", err)
    duration = re.search(r"Duration: (\d+):(\d+):([\d.]+)", err)
    assert video and duration, err
    h, m, s = duration.groups()
    return {"codec": video[1], "pix_fmt": video[2], "size": (int(video[3]), int(video[4])),
            "duration": int(h) * 3600 + int(m) * 60 + float(s)}


def decode(path: Path) -> np.ndarray:
    with imageio.get_reader(path) as reader:
        return np.stack(list(reader.iter_data()))


@pytest.fixture(scope="module")
def cheetah():
    """(a render env, a 60-step trajectory recorded on another env of the task)."""
    with make_env("dmc:cheetah_run", 0) as source, make_env("dmc:cheetah_run", 1) as env:
        traj = record(source, 60)
        yield env, traj


def test_cheetah_clip_is_a_browser_mp4_of_the_segment(cheetah, tmp_path):
    env, traj = cheetah
    cfg = ClipConfig()
    frames = render_segment(env, traj.states, traj.context, 5, 50, cfg)
    assert frames.shape == (50, 256, 256, 3) and frames.dtype == np.uint8  # the default size
    path = encode_mp4(frames, tmp_path / "clip.mp4", cfg)

    assert path == tmp_path / "clip.mp4"
    assert os.listdir(tmp_path) == ["clip.mp4"]  # no temporary file left behind
    info = probe(path)
    assert info["codec"] == "h264" and info["pix_fmt"] == "yuv420p"
    assert info["size"] == (256, 256)  # not padded to a macro block
    # One frame per step at 100/3 fps: 50 steps in 1.5 s, as the paper's labellers saw them.
    assert info["duration"] == pytest.approx(1.5, abs=0.05)
    data = path.read_bytes()
    assert data.index(b"moov") < data.index(b"mdat")  # faststart: playable while loading

    decoded = decode(path)
    assert decoded.shape == frames.shape
    assert np.abs(decoded.astype(np.int16) - frames).mean() < 10
    # The cheetah moves: consecutive frames differ.
    assert all(np.abs(decoded[i + 1].astype(np.int16) - decoded[i]).mean() > 0.1
               for i in range(0, 49, 7))


def test_clip_shows_the_stored_states_not_the_env_now(cheetah):
    env, traj = cheetah
    cfg = ClipConfig(width=64, height=64)
    first = render_segment(env, traj.states, traj.context, 0, 10, cfg)
    env.reset()
    for _ in range(20):
        env.step(np.ones(env.action_dim, np.float32))
    render_segment(env, traj.states, traj.context, 40, 10, cfg)  # elsewhere in the trajectory
    again = render_segment(env, traj.states, traj.context, 0, 10, cfg)
    np.testing.assert_array_equal(again, first)


def test_render_quality_settings_take_effect(cheetah):
    env, traj = cheetah
    fast = ClipConfig(width=64, height=64)
    model_own = ClipConfig(width=64, height=64, shadow_size=None, multisamples=None)
    no_shadow = ClipConfig(width=64, height=64, shadow_size=0)
    # Each change of settings replaces the cached renderer, in either direction.
    a = render_segment(env, traj.states, traj.context, 20, 3, fast)
    b = render_segment(env, traj.states, traj.context, 20, 3, no_shadow)
    c = render_segment(env, traj.states, traj.context, 20, 3, model_own)
    assert not np.array_equal(a, b) and not np.array_equal(a, c)
    np.testing.assert_array_equal(render_segment(env, traj.states, traj.context, 20, 3, fast), a)
    # The floor's mirror image is left out by default, and back when asked for.
    mirrored = ClipConfig(width=64, height=64, reflections=True)
    d = render_segment(env, traj.states, traj.context, 20, 3, mirrored)
    assert not np.array_equal(a, d)
    np.testing.assert_array_equal(render_segment(env, traj.states, traj.context, 20, 3, fast), a)


def test_metaworld_query_clips(tmp_path):
    with make_env("metaworld:door-open", 0) as source, make_env("metaworld:door-open", 1) as env:
        traj0, traj1 = record(source, 30, seed=0), record(source, 30, seed=1)
        cfg = ClipConfig(width=64, height=64)
        names = render_query_clips(env, traj0, 0, traj1, 10, 20, tmp_path / "clips", "q7", cfg)
        assert names == ("q7-0.mp4", "q7-1.mp4")
        assert sorted(os.listdir(tmp_path / "clips")) == list(names)
        for name, traj, start in zip(names, (traj0, traj1), (0, 10), strict=True):
            decoded = decode(tmp_path / "clips" / name)
            assert decoded.shape == (20, 64, 64, 3)
            frames = render_segment(env, traj.states, traj.context, start, 20, cfg)
            assert np.abs(decoded.astype(np.int16) - frames).mean() < 10
            assert probe(tmp_path / "clips" / name)["size"] == (64, 64)


@pytest.mark.parametrize("kwargs, field", [
    ({"width": 127}, "width"), ({"height": 129}, "height"), ({"width": 1024}, "width"),
    ({"height": 32}, "height"), ({"width": 200, "macro_block_size": 16}, "width"),
    ({"fps": 0}, "fps"), ({"crf": 60}, "crf"), ({"shadow_size": -1}, "shadow_size"),
])
def test_bad_config_is_refused(kwargs, field):
    with pytest.raises(ValueError, match=field):
        ClipConfig(**kwargs)


def test_bad_segment_and_names_are_refused(cheetah, tmp_path):
    env, traj = cheetah
    cfg = ClipConfig(width=64, height=64)
    with pytest.raises(ValueError, match="does not fit"):
        iter_segment_frames(env, traj.states, traj.context, 30, 50, cfg)
    with pytest.raises(ValueError, match="stem"):
        render_query_clips(env, traj, 0, traj, 0, 5, tmp_path, "../q", cfg)
    with pytest.raises(ValueError, match="does not fit"):  # the second side: no file at all
        render_query_clips(env, traj, 0, traj, 58, 5, tmp_path, "q", cfg)
    with pytest.raises(ValueError, match="no frames"):
        encode_mp4([], tmp_path / "x.mp4", cfg)
    with pytest.raises(ValueError, match="frame 0"):
        encode_mp4(np.zeros((3, 66, 64, 3), np.uint8), tmp_path / "x.mp4", cfg)
    assert os.listdir(tmp_path) == []


OSMESA_SCRIPT = """
import sys
import mujoco
import numpy as np
from trainer.clips import ClipConfig, encode_mp4, render_segment
from trainer.envs import make_env
assert mujoco.gl_context.GLContext.__module__ == "mujoco.osmesa", mujoco.gl_context.GLContext
states = np.load(sys.argv[1])
cfg = ClipConfig(width=64, height=64)
with make_env("dmc:cheetah_run", 0) as env:
    frames = render_segment(env, states, 0, 0, len(states), cfg)
np.save(sys.argv[2], frames)
encode_mp4(frames, sys.argv[3], cfg)
"""


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="libosmesa6 missing")
def test_osmesa_renders_the_same_clip(cheetah, tmp_path):
    env, traj = cheetah
    states = traj.states[10:20]
    np.save(tmp_path / "states.npy", states)
    subprocess.run(
        [sys.executable, "-c", OSMESA_SCRIPT, str(tmp_path / "states.npy"),
         str(tmp_path / "frames.npy"), str(tmp_path / "clip.mp4")],
        cwd=REPO, check=True, timeout=120,
        env={**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"},
    )
    osmesa = np.load(tmp_path / "frames.npy")
    egl = render_segment(env, states, 0, 0, 10, ClipConfig(width=64, height=64))
    assert np.abs(osmesa.astype(np.int16) - egl).mean() < 2  # both Mesa's llvmpipe
    assert decode(tmp_path / "clip.mp4").shape == (10, 64, 64, 3)


def test_a_runs_clip_size_sets_the_frame_size(cheetah, tmp_path):
    env, traj = cheetah
    for name, (width, height) in CLIP_SIZES.items():
        cfg = sized(ClipConfig(), name)
        names = render_query_clips(env, traj, 0, traj, 10, 8, tmp_path, f"s{name}", cfg)
        assert {probe(tmp_path / n)["size"] for n in names} == {(width, height)}
    assert sized(ClipConfig(width=64, height=64), None) == ClipConfig(width=64, height=64)


@pytest.mark.parametrize("domain", sorted(CLIP_CAMERAS))
def test_walkers_and_runners_are_filmed_by_a_camera_that_follows_them(domain):
    """Each clip camera exists in its domain's model and tracks the body's centre of mass, so
    the body stays in frame however far it runs."""
    import mujoco
    from dm_control import suite

    task = next(t for d, t in suite.ALL_TASKS if d == domain)
    physics = suite.load(domain, task).physics
    model = physics.model.ptr
    camera = model.camera(CLIP_CAMERAS[domain])
    assert camera.mode[0] == mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM
    assert clip_camera(f"dmc:{domain}_{task}") == CLIP_CAMERAS[domain]
    assert clip_camera("dmc:cartpole_swingup") is None and clip_camera("metaworld:reach") is None


def test_a_cheetah_that_runs_off_stays_in_the_clip(cheetah):
    """Moved 20 m along its track, the cheetah is still in the middle of the frame."""
    env, traj = cheetah
    states = traj.states[:1].copy()
    moved = states.copy()
    moved[0, 0] += 20.0  # rootx: 20 m forward
    frames = [render_segment(env, s, traj.context, 0, 1, ClipConfig(width=64, height=64))[0]
              for s in (states, moved)]
    # The camera moved with it: the two frames are alike (a fixed camera's differ by ~12.6 grey
    # levels on average: the cheetah is gone from its view).
    assert np.abs(frames[1].astype(np.int16) - frames[0]).mean() < 2


def test_step_seconds_match_the_installed_suites():
    from dm_control import suite

    seen: dict[str, float] = {}
    for domain, task in suite.ALL_TASKS:
        if domain not in seen:
            seen[domain] = suite.load(domain, task).control_timestep()
            assert step_seconds(f"dmc:{domain}_{task}") == pytest.approx(seen[domain]), domain
    with make_env("metaworld:door-open", 0) as env:
        assert env._env.dt == pytest.approx(METAWORLD_STEP_S)

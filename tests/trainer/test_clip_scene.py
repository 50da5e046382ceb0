"""What a clip's frame is made of: the body at its task's share of the frame's height, ground over
the lower part of the frame and a plain sky above it (trainer.clips `CAMERA_DISTANCES`,
`GROUND_REACH`, `SKY_RGB`). `benchmarks/bench_ground.py` measures the same over many clips."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported; the project default

import dataclasses

import mujoco
import numpy as np
import pytest

from trainer.clips import (
    BODY_SHARE,
    BODY_WIDTH_SHARE,
    CAMERA_DISTANCES,
    SKY_RGB,
    ClipConfig,
    clip_camera,
    frame_shares,
    moved_states,
    render_segment,
)
from trainer.envs import make_env

CFG = ClipConfig(width=128, height=128)
SIDE_FILMED = ["dmc:cheetah_run", "dmc:walker_run", "dmc:hopper_hop"]


def standing(env) -> np.ndarray:
    """One state: a DMC body as modelled (standing), Metaworld's arm as an episode starts."""
    env.reset()
    if env.task.startswith("dmc:"):
        mujoco.mj_resetData(env._model, env._data)
        mujoco.mj_forward(env._model, env._data)
    return np.array([env.physics_state()])


@pytest.mark.parametrize("task", [*SIDE_FILMED, "dmc:quadruped_run", "metaworld:door-open"])
def test_the_standing_body_fills_its_share_of_the_frame(task):
    """The body's height is BODY_SHARE of the frame's, or its length BODY_WIDTH_SHARE of the
    width where the height would make it longer (cheetah, quadruped). Metaworld's fixed corner
    camera keeps the model's view (the objects and the goal must stay in it): its arm fills more
    than half the frame's height as it is."""
    with make_env(task, 0) as env:
        shares = frame_shares(env, standing(env), env.episode_context(), 0, 1, CFG)
    height, width = shares["body_height"][0], shares["body_width"][0]
    print(f"{task}: body {height:.2f} of the frame's height, {width:.2f} of its width")
    if task.startswith("metaworld:"):
        assert 0.5 <= height <= 0.9
    elif width < BODY_WIDTH_SHARE - 0.05:
        assert height == pytest.approx(BODY_SHARE, abs=0.03), (task, height, width)
    else:
        assert width == pytest.approx(BODY_WIDTH_SHARE, abs=0.05), (task, height, width)
        assert height <= BODY_SHARE
    assert set(CAMERA_DISTANCES) == {"cheetah", "walker", "hopper", "quadruped"}


def sky_pixels(env, frame: np.ndarray, cfg: ClipConfig) -> np.ndarray:
    """(n, 3): the frame's pixels where nothing is drawn (env still at the frame's state)."""
    ids = env.segmentation(cfg.width, cfg.height, clip_camera(env.task))
    return frame[ids[..., 1] < 0].astype(int)


@pytest.mark.parametrize("task", SIDE_FILMED)
def test_ground_below_a_plain_sky_wherever_the_body_is(task):
    """The lowest quarter of the frame is all ground (or the body on it), at the start and 1 km
    along the run, and the sky above is one plain colour: no starfield."""
    with make_env(task, 0) as env:
        one = standing(env)
        for dx in (0.0, 1000.0):
            moved = moved_states(env, one, dx)
            shares = frame_shares(env, moved, 0, 0, 1, CFG)
            assert shares["sky_below"][0] == 0, (task, dx)
            assert shares["ground"][0] > 0.3, (task, dx, shares["ground"])
            frame = render_segment(env, moved, 0, 0, 1, CFG)[0]
            sky = sky_pixels(env, frame, CFG)
            if task != "dmc:walker_run":  # its camera looks down: ground to the top
                assert len(sky) > 0.1 * CFG.width * CFG.height, (task, dx)
            assert np.all(np.abs(sky - np.round(np.array(SKY_RGB) * 255)) <= 1), (task, dx)


def test_without_the_cues_the_scene_is_the_models_own():
    """Turned off, the cues give back the model's floor sizes and its starry skybox."""
    with make_env("dmc:cheetah_run", 0) as env, make_env("dmc:cheetah_run", 1) as fresh:
        one = standing(env)
        render_segment(env, one, 0, 0, 1, CFG)
        assert not np.array_equal(env._model.geom_size, fresh._model.geom_size)
        bare = dataclasses.replace(CFG, motion_cues=False)
        frame = render_segment(env, one, 0, 0, 1, bare)[0]
        assert np.array_equal(env._model.geom_size, fresh._model.geom_size)
        assert np.array_equal(env._model.tex_data, fresh._model.tex_data)
        assert sky_pixels(env, frame, bare).std(axis=0).max() > 5  # stars on a gradient

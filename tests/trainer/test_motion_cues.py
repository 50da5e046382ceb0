"""Clips show motion wherever the agent is: the ground in every frame (the floor drawn under the
body by whole periods of its grid) and, beside planar runners, distance posts fixed in the world
(trainer.clips, `MotionCues` in trainer.scene). `benchmarks/bench_ground.py` runs the same check
over many clips."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported; the project default

import dataclasses

import numpy as np
import pytest

from trainer.clips import (
    GROUND_MIN_FRACTION,
    MARKER_ROWS,
    ClipConfig,
    ground_fractions,
    motion_cues,
    moved_states,
    render_segment,
)
from trainer.envs import make_env

SMALL = ClipConfig(width=64, height=64)
FAR = 1000.0  # metres: past the end of every DMC floor (cheetah's ends at 198, walker's at 498)
TASKS = ["dmc:cheetah_run", "dmc:walker_run", "dmc:hopper_hop", "dmc:quadruped_run"]


def states_of(env, steps: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    env.reset()
    states = []
    for _ in range(steps):
        states.append(env.physics_state())
        env.step(rng.uniform(-1, 1, env.action_dim).astype(np.float32))
    return np.array(states)


@pytest.fixture(scope="module", params=TASKS)
def recorded(request):
    with make_env(request.param, 0) as env:
        yield env, states_of(env, 12)


def test_no_frame_without_ground_however_far_the_agent_went(recorded):
    env, states = recorded
    dys = (0.0, 300.0) if env.task == "dmc:quadruped_run" else (0.0,)  # it runs in the plane
    for dx in (-40.0, 0.0, 150.0, FAR):
        for dy in dys:
            moved = moved_states(env, states, dx, dy)
            fractions = ground_fractions(env, moved, 0, 0, len(states), SMALL)
            assert fractions.min() >= GROUND_MIN_FRACTION, (env.task, dx, dy, fractions)


def test_the_check_finds_the_frames_without_ground_of_the_scene_as_modelled(recorded):
    """Without the cues, far along the run the floor is out of every frame: what the labellers
    saw (16 of 60 cheetah clips of the demo run) and what the check above would catch."""
    env, states = recorded
    bare = dataclasses.replace(SMALL, motion_cues=False)
    fractions = ground_fractions(env, moved_states(env, states, FAR, FAR), 0, 0, len(states),
                                 bare)
    assert fractions.max() < GROUND_MIN_FRACTION
    at_start = ground_fractions(env, states, 0, 0, len(states), bare)
    assert at_start.min() >= GROUND_MIN_FRACTION


def test_half_a_metre_further_shows_in_the_frame(recorded):
    """The same pose half a metre further along: without the cues, a side-filmed runner past the
    floor renders the very same pixels (no speed, no direction to see); with them it does not."""
    env, states = recorded
    one = states[-1:]
    frames = {}
    for on in (False, True):
        cfg = dataclasses.replace(SMALL, motion_cues=on)
        frames[on] = [render_segment(env, moved_states(env, one, dx), 0, 0, 1, cfg)[0]
                      for dx in (FAR, FAR + 0.5)]
    assert not np.array_equal(*frames[True])
    if env.task in ("dmc:cheetah_run", "dmc:hopper_hop"):  # filmed level, so only sky behind
        assert np.array_equal(*frames[False])


def test_the_floor_and_posts_stay_fixed_in_the_world(recorded):
    """10 m is a whole number of grid periods (2 m) and of post cycles (5 m): the same pose 10 m
    further renders the very same frame, so the floor did not travel with the body."""
    env, states = recorded
    one = states[-1:]
    a, b = (render_segment(env, moved_states(env, one, dx), 0, 0, 1, SMALL)[0]
            for dx in (FAR, FAR + 10.0))
    assert np.array_equal(a, b)


def test_planar_runners_have_posts_and_others_do_not():
    assert set(MARKER_ROWS) == {"cheetah", "walker", "hopper"}
    cues = motion_cues("dmc:cheetah_run")
    assert cues is not None and cues.ground_follows and cues.marker_row == MARKER_ROWS["cheetah"]
    quadruped = motion_cues("dmc:quadruped_run")
    assert quadruped is not None and quadruped.marker_row is None
    assert motion_cues("metaworld:door-open") is None


def test_posts_are_drawn_beside_the_track():
    """Red at the start, yellow every 5 m: in a cheetah frame at x = 0 some red pixels show, and
    at x = 1000 yellow ones (the post at 1000 m) but no red."""
    with make_env("dmc:cheetah_run", 0) as env:
        one = states_of(env, 1)
        cfg = ClipConfig(width=128, height=128)

        def share(frame, rgb):
            return float(np.mean(np.all(np.abs(frame.astype(int) - rgb) < 40, axis=-1)))

        start = render_segment(env, one, 0, 0, 1, cfg)[0]
        far = render_segment(env, moved_states(env, one, FAR), 0, 0, 1, cfg)[0]
        red, yellow = (240, 70, 70), (240, 240, 70)  # as lit
        assert share(start, red) > 0 and share(far, red) == 0
        assert share(far, yellow) > 0


def test_every_following_camera_task_keeps_its_ground():
    """Every DMC domain whose clip camera follows the body, a few steps at the start and far
    along (the cameras of the others never move, so their frame is the fixed reference)."""
    from trainer.clips import CLIP_CAMERAS

    tasks = {"humanoid": "dmc:humanoid_run", "humanoid_CMU": "dmc:humanoid_CMU_run",
             "dog": "dmc:dog_run", "fish": "dmc:fish_swim", "swimmer": "dmc:swimmer_swimmer6"}
    assert set(tasks) | {"cheetah", "walker", "quadruped", "hopper"} == set(CLIP_CAMERAS)
    for task in tasks.values():
        with make_env(task, 0) as env:
            states = states_of(env, 3)
            for dx in ((0.0, 0.3) if task == "dmc:fish_swim" else (0.0, FAR)):  # in its tank
                fractions = ground_fractions(env, moved_states(env, states, dx, dx), 0, 0, 3,
                                             SMALL)
                assert fractions.min() >= GROUND_MIN_FRACTION, (task, dx, fractions)

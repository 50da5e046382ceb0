"""The episode store a worker keeps for the dataset export: a finished trajectory with its final
observation and state, from the state kept as the episode ended or, without one, recomputed."""

from __future__ import annotations

import numpy as np

from rundata.episodes import read_episode, stored_trajectories, write_episode
from trainer.envs import make_env
from trainer.queue_hooks import stored_episode
from trainer.trajectories import EpisodeRecorder


def _episode(length: int = 30):
    """A random-action trajectory of `length` steps, and the observation and state after it."""
    env = make_env("dmc:cheetah_run", 3, length)
    obs = env.reset()
    recorder = EpisodeRecorder(env.obs_dim, env.action_dim, len(env.physics_state()), length)
    rng = np.random.default_rng(0)
    done = False
    while not done:
        action = rng.uniform(-1, 1, env.action_dim).astype(np.float32)
        state = env.physics_state()
        result = env.step(action)
        recorder.record(obs, action, result.reward, state, result.success)
        obs, done = result.obs, result.done
    return recorder.finish(7, env.episode_context()), obs, env.physics_state()


def test_the_final_observation_is_restored_exactly_from_the_end_state(tmp_path):
    traj, final_obs, end_state = _episode()
    other = make_env("dmc:cheetah_run", 99, 30)
    episode = stored_episode(traj, other, end_state)
    assert episode.observations.shape == (31, 17) and episode.states.shape == (31, 18)
    np.testing.assert_array_equal(episode.observations[:-1], traj.obs)
    np.testing.assert_array_equal(episode.observations[-1], final_obs)
    np.testing.assert_array_equal(episode.states[-1], end_state)
    assert not episode.final_resimulated

    write_episode(tmp_path, episode)
    assert stored_trajectories(tmp_path) == [7]
    back = read_episode(tmp_path, 7)
    for name in ("observations", "actions", "rewards", "states"):
        np.testing.assert_array_equal(getattr(back, name), getattr(episode, name))
    assert (back.context, back.success, back.skill) == (0, False, None)
    assert [p.name for p in tmp_path.iterdir()] == ["episode-7.npz"]  # no temporary file left


def test_without_an_end_state_the_last_step_is_stepped_again(tmp_path):
    traj, final_obs, end_state = _episode()
    episode = stored_episode(traj, make_env("dmc:cheetah_run", 99, 30), None)
    assert episode.final_resimulated
    np.testing.assert_array_equal(episode.observations[:-1], traj.obs)
    np.testing.assert_allclose(episode.observations[-1], final_obs, rtol=0, atol=1e-5)
    np.testing.assert_allclose(episode.states[-1], end_state, rtol=0, atol=1e-6)

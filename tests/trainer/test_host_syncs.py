"""A GPU run's step waits for the GPU once, when the action comes back: the transition and
the observation go to the device asynchronously, and the learned reward of the transition is
computed on the host. On the CPU the paths a GPU takes are forced and must store and return
what the NumPy paths do; on a GPU (skipped without one) torch's sync debug mode counts the
waits."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from runvocab.config import SACConfig, build_config
from trainer.agent_reward import AgentReward
from trainer.feedback import LabelLog, PreferenceFeedback
from trainer.gpu_waits import GpuWaits, waits_in
from trainer.replay_buffer import ReplayBuffer
from trainer.reward_model import RewardModel
from trainer.sac import SAC
from trainer.skills.agent import SkillReplayBuffer
from trainer.teachers import make_teacher

OBS, ACT, SKILL = 4, 2, 3
CPU = torch.device("cpu")
needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")


def transitions(n: int, seed: int = 0) -> list[tuple]:
    rng = np.random.default_rng(seed)
    f32 = np.float32
    return [(rng.normal(size=OBS).astype(f32), rng.uniform(-1, 1, ACT).astype(f32),
             float(rng.normal()), float(rng.normal()), rng.normal(size=OBS).astype(f32),
             rng.normal(size=SKILL).astype(f32)) for _ in range(n)]


def forced_device_path(buffer: ReplayBuffer) -> ReplayBuffer:
    buffer._arrays = None  # what a GPU buffer has: no NumPy views of its memory
    return buffer


def stored(buffer: ReplayBuffer) -> list[torch.Tensor]:
    return [field[: buffer.size].cpu() for field in buffer._fields]


@pytest.mark.parametrize("with_skill", [False, True])
def test_the_devices_one_copy_row_stores_what_the_numpy_views_store(with_skill: bool) -> None:
    def make() -> ReplayBuffer:
        if with_skill:
            return SkillReplayBuffer(OBS, ACT, SKILL, 8, CPU, seed=0)
        return ReplayBuffer(OBS, ACT, 8, CPU, seed=0)

    plain, device_path = make(), forced_device_path(make())
    for obs, action, reward, true_reward, next_obs, skill in transitions(11):
        plain.add(obs, action, reward, true_reward, next_obs, skill)
        device_path.add(obs, action, reward, true_reward, next_obs, skill)
    assert plain.size == device_path.size == 8 and plain.cursor == device_path.cursor == 3
    for a, b in zip(stored(plain), stored(device_path), strict=True):
        assert torch.equal(a, b)
    assert len(plain._fields) == (6 if with_skill else 5)


def test_the_torch_actors_one_read_back_acts_as_the_numpy_actor() -> None:
    torch.manual_seed(0)
    agent = SAC(OBS, ACT, SACConfig(hidden_dim=16, hidden_layers=2, batch_size=8), CPU)
    obs = np.random.default_rng(1).normal(size=OBS).astype(np.float32)
    numpy_side = [agent.act(obs, np.random.default_rng(2), deterministic=d) for d in (True, False)]
    agent._numpy_actor = None  # the path a GPU agent takes
    torch_side = [agent.act(obs, np.random.default_rng(2), deterministic=d) for d in (True, False)]
    for a, b in zip(numpy_side, torch_side, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(torch_side[0], torch_side[1])  # the second one drew noise


def learned_reward(tmp_path, device: torch.device) -> AgentReward:
    cfg = build_config("dmc:cheetah_run", "tiny", {"algo": "pebble"})
    torch.manual_seed(0)
    model = RewardModel(OBS, ACT, cfg.reward, device, 0)
    teacher = make_teacher(cfg.teacher, 0, cfg.feedback.segment_length, 100)
    feedback = PreferenceFeedback(cfg.feedback, model, teacher, "scripted:noisy",
                                  LabelLog(str(tmp_path / "labels.jsonl")),
                                  np.random.default_rng(1))
    feedback.rounds = 1  # r_hat from here on
    return AgentReward(cfg, ReplayBuffer(OBS, ACT, 16, device, seed=0), feedback, device)


def test_the_learned_reward_of_a_new_transition_is_the_models_and_follows_each_round(
        tmp_path) -> None:
    reward = learned_reward(tmp_path, CPU)
    model = reward.feedback.model
    obs, action, *_ = transitions(1)[0]

    def models_reward() -> float:
        with torch.no_grad():
            return float(model.reward(torch.from_numpy(obs)[None], torch.from_numpy(action)[None]))

    assert reward.at_step(obs, action, 0.0) == pytest.approx(models_reward(), abs=1e-6)
    host_model = reward._host_reward
    reward.at_step(obs, action, 0.0)
    assert reward._host_reward is host_model  # not made again within a round
    # A round replaces what the host model was made from (as a GPU run's copy goes stale):
    # parameters that are new tensors, not the ones its views see.
    with torch.no_grad():
        for layer in model.ensemble.layers:
            if hasattr(layer, "weight"):
                layer.weight = torch.nn.Parameter(layer.weight * 2)
    assert reward.at_step(obs, action, 0.0) != pytest.approx(models_reward(), abs=1e-6)
    reward.feedback.rounds += 1
    assert reward.at_step(obs, action, 0.0) == pytest.approx(models_reward(), abs=1e-6)


def waits_for_the_gpu(action) -> list[str]:
    """Where `action()` made the host wait for the GPU, one entry a wait: the caller's line and
    torch's message, so a failure names the wait."""
    torch.cuda.synchronize()
    with GpuWaits() as waits:
        action()
    return waits.where()


def test_only_torchs_per_wait_message_counts_as_a_wait() -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warnings.warn("Synchronization debug mode is a prototype feature and does not yet "
                      "detect all synchronizing operations", stacklevel=1)
        warnings.warn("called a synchronizing CUDA operation", stacklevel=1)
    assert [str(w.message) for w in waits_in(caught)] == ["called a synchronizing CUDA operation"]


@needs_cuda
def test_on_a_gpu_a_step_waits_once_when_the_action_comes_back(tmp_path) -> None:
    cuda = torch.device("cuda")
    obs, action, reward, true_reward, next_obs, skill = transitions(1)[0]
    agent = SAC(OBS + SKILL, ACT, SACConfig(hidden_dim=16, hidden_layers=2, batch_size=8), cuda)
    rng = np.random.default_rng(0)
    agent.act(np.concatenate([obs, skill]), rng)  # the first call sets up the device's libraries
    waits = waits_for_the_gpu(lambda: agent.act(np.concatenate([obs, skill]), rng))
    assert len(waits) == 1, waits

    r_hat = learned_reward(tmp_path, cuda)
    buffer = SkillReplayBuffer(OBS, ACT, SKILL, 16, cuda, seed=0)

    def store() -> None:
        buffer.add(obs, action, r_hat.at_step(obs, action, true_reward), true_reward, next_obs,
                   skill)

    store()
    assert waits_for_the_gpu(store) == []
    expected = r_hat.feedback.model.reward(torch.from_numpy(obs)[None].to(cuda),
                                           torch.from_numpy(action)[None].to(cuda))
    torch.testing.assert_close(buffer.reward[:2, 0], expected.expand(2))
    torch.testing.assert_close(buffer.skill[1].cpu(), torch.from_numpy(skill))


@needs_cuda
def test_on_a_gpu_successive_actions_are_the_cpu_actors_for_their_own_observations() -> None:
    """The observation goes through one reused pinned buffer: each action must still be the
    one for its own observation."""
    torch.manual_seed(0)
    cfg = SACConfig(hidden_dim=16, hidden_layers=2, batch_size=8)
    on_gpu = SAC(OBS, ACT, cfg, torch.device("cuda"))
    on_cpu = SAC(OBS, ACT, cfg, CPU)
    on_cpu.actor.load_state_dict({k: v.cpu() for k, v in on_gpu.actor.state_dict().items()})
    for obs, *_ in transitions(5, seed=3):
        for deterministic in (True, False):
            gpu_action = on_gpu.act(obs, np.random.default_rng(4), deterministic)
            cpu_action = on_cpu.act(obs, np.random.default_rng(4), deterministic)
            np.testing.assert_allclose(gpu_action, cpu_action, rtol=1e-5, atol=1e-6)

import math

import numpy as np
import torch
from torch.distributions import Normal, TransformedDistribution
from torch.distributions.transforms import TanhTransform

from runvocab.config import SACConfig
from trainer.replay_buffer import ReplayBuffer
from trainer.sac import SAC

CFG = SACConfig(hidden_dim=32, hidden_layers=2, batch_size=16)


def test_log_prob_is_the_squashed_gaussian_density():
    torch.manual_seed(0)
    agent = SAC(5, 3, CFG, torch.device("cpu"))
    obs = torch.randn(64, 5)
    torch.manual_seed(1)
    action, log_prob = agent.actor.sample(obs)
    mean, log_std = agent.actor(obs)
    dist = TransformedDistribution(Normal(mean, log_std.exp()), [TanhTransform()])
    u = torch.atanh(action.clamp(-1 + 1e-6, 1 - 1e-6))
    expected = (Normal(mean, log_std.exp()).log_prob(u)
                - torch.log1p(-torch.tanh(u) ** 2)).sum(-1, keepdim=True)
    torch.testing.assert_close(log_prob, expected, rtol=1e-3, atol=1e-3)
    assert torch.all(action.abs() < 1)
    # the same density as torch's own tanh-transformed Normal
    torch.testing.assert_close(dist.log_prob(action.clamp(-1 + 1e-6, 1 - 1e-6)).sum(-1, True),
                               expected, rtol=1e-2, atol=1e-2)


def test_the_actor_learns_its_standard_deviation_per_state():
    torch.manual_seed(0)
    agent = SAC(5, 3, CFG, torch.device("cpu"))
    _, log_std = agent.actor(torch.randn(10, 5))
    assert log_std.std(dim=0).min() > 0  # a function of the state, not a fixed constant
    assert torch.all(log_std >= CFG.log_std_min) and torch.all(log_std <= CFG.log_std_max)
    assert any(p.requires_grad for p in agent.actor.trunk[-1].parameters())


def test_numpy_acting_matches_the_torch_actor():
    torch.manual_seed(0)
    agent = SAC(5, 3, CFG, torch.device("cpu"))
    obs = np.random.default_rng(0).normal(size=5).astype(np.float32)
    mean, _ = agent.actor(torch.from_numpy(obs)[None])
    np.testing.assert_allclose(agent.act(obs, np.random.default_rng(0), deterministic=True),
                               torch.tanh(mean)[0].detach().numpy(), rtol=1e-5, atol=1e-6)
    # after an update the NumPy path still sees the current weights
    buffer = ReplayBuffer(5, 3, 100, torch.device("cpu"), seed=0)
    for _ in range(50):
        buffer.add(np.random.randn(5).astype(np.float32), np.random.uniform(-1, 1, 3).astype(
            np.float32), 1.0, 1.0, np.random.randn(5).astype(np.float32))
    for _ in range(5):
        agent.update(buffer.sample(16))
    mean, _ = agent.actor(torch.from_numpy(obs)[None])
    np.testing.assert_allclose(agent.act(obs, np.random.default_rng(0), deterministic=True),
                               torch.tanh(mean)[0].detach().numpy(), rtol=1e-5, atol=1e-6)


def test_update_schedule_temperature_and_target():
    torch.manual_seed(0)
    agent = SAC(5, 3, CFG, torch.device("cpu"))
    assert math.isclose(agent.alpha.item(), 0.2, rel_tol=1e-6)
    buffer = ReplayBuffer(5, 3, 100, torch.device("cpu"), seed=0)
    for _ in range(50):
        buffer.add(np.random.randn(5).astype(np.float32), np.zeros(3, np.float32), 1.0, 1.0,
                   np.random.randn(5).astype(np.float32))
    target_before = [p.clone() for p in agent.critic_target.parameters()]
    metrics = agent.update(buffer.sample(16))  # update 0: the target moves (every 2 updates)
    assert set(metrics) >= {"critic_loss", "actor_loss", "alpha", "entropy"}
    # Read when logged, not at each update: 0-d tensors, off the graph.
    assert all(v.dim() == 0 and not v.requires_grad for v in metrics.values())
    # Polyak: target <- (1 - tau) target + tau critic, with the critic after its step
    for t0, t1, c1 in zip(target_before, agent.critic_target.parameters(),
                          agent.critic.parameters(), strict=True):
        torch.testing.assert_close(t1, (1 - CFG.tau) * t0 + CFG.tau * c1)
    target_mid = [p.clone() for p in agent.critic_target.parameters()]
    agent.update(buffer.sample(16))  # update 1: no target update
    assert all(torch.equal(a, b) for a, b in zip(target_mid, agent.critic_target.parameters(),
                                                 strict=True))
    # the temperature is learned
    assert not math.isclose(agent.alpha.item(), 0.2, rel_tol=1e-7)


def test_critic_reset_gives_fresh_critic_and_target():
    torch.manual_seed(0)
    agent = SAC(5, 3, CFG, torch.device("cpu"))
    actor_before = [p.clone() for p in agent.actor.parameters()]
    critic_before = [p.clone() for p in agent.critic.parameters()]
    agent.reset_critic()
    assert not all(torch.equal(a, b) for a, b in zip(critic_before, agent.critic.parameters(),
                                                     strict=True))
    assert all(torch.equal(a, b) for a, b in zip(agent.critic.parameters(),
                                                 agent.critic_target.parameters(), strict=True))
    assert all(torch.equal(a, b) for a, b in zip(actor_before, agent.actor.parameters(),
                                                 strict=True))


def test_a_buffer_resumes_its_sampling_stream_and_takes_another_devices_state():
    def filled(seed: int) -> ReplayBuffer:
        buffer = ReplayBuffer(2, 1, 100, torch.device("cpu"), seed=seed)
        for i in range(60):
            buffer.add(np.full(2, i, np.float32), np.zeros(1, np.float32), 0.0, 0.0,
                       np.zeros(2, np.float32))
        return buffer

    buffer = filled(0)
    buffer.indices(8)
    state = buffer.state_dict()
    expected = buffer.indices(8)
    resumed = filled(1)
    resumed.load_state_dict(state)
    assert torch.equal(resumed.indices(8), expected)  # the same stream, on from where it was
    # A state saved by a generator of another device (a CUDA generator's is 16 bytes): the
    # buffer carries on with a stream seeded by it, the same one at every resume.
    foreign = state | {"generator": torch.arange(16, dtype=torch.uint8)}
    first, second = filled(2), filled(3)
    first.load_state_dict(foreign)
    second.load_state_dict(foreign)
    drawn = first.indices(32)
    assert torch.equal(drawn, second.indices(32)) and int(drawn.max()) < 60

"""Skill discovery backends (APS, DIAYN, CIC) and the skill-conditioned agent, on toy batches."""

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch import nn

from runvocab.config import SACConfig, SkillConfig
from trainer.entropy import RunningMeanStd
from trainer.skills import (
    SKILL_BACKENDS,
    SkillAgent,
    SkillBatch,
    SkillReplayBuffer,
    make_skill_backend,
    particle_entropy,
)

CPU = torch.device("cpu")
OBS_DIM, ACTION_DIM = 6, 2
SKILL = SkillConfig(hidden_dim=32, knn_k=3, lr=1e-3)
SAC_CFG = SACConfig(hidden_dim=32, hidden_layers=2, batch_size=16)


def _batch(backend, n: int = 16, seed: int = 0) -> SkillBatch:
    g = torch.Generator().manual_seed(seed)
    skill = torch.from_numpy(backend.sample_skills(np.random.default_rng(seed), n))
    return SkillBatch(torch.randn(n, OBS_DIM, generator=g), torch.rand(n, ACTION_DIM, generator=g),
                      torch.zeros(n, 1), torch.randn(n, OBS_DIM, generator=g), skill)


def _backend(name: str, **changes):
    torch.manual_seed(0)
    cfg = dataclasses.replace(SKILL, **changes)
    return make_skill_backend(name, OBS_DIM, cfg, CPU)


# -- skill spaces -------------------------------------------------------------------------------

def test_each_backend_samples_from_its_own_skill_space():
    rng = np.random.default_rng(0)
    aps, diayn, cic = (_backend(n) for n in ("aps", "diayn", "cic"))
    assert (aps.skill_dim, diayn.skill_dim, cic.skill_dim) == (10, 16, 64)  # the papers' sizes

    z = aps.sample_skills(rng, 4000)
    assert z.shape == (4000, 10) and z.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(z, axis=1), 1.0, rtol=1e-5)
    assert np.abs(z.mean(axis=0)).max() < 0.03  # no preferred direction on the sphere

    z = diayn.sample_skills(rng, 16_000)
    assert set(np.unique(z)) == {0.0, 1.0} and np.all(z.sum(axis=1) == 1)  # one-hot
    counts = z.sum(axis=0)
    assert counts.min() > 850 and counts.max() < 1150  # each of 16 skills ~1000 times

    z = cic.sample_skills(rng, 4000)
    assert z.shape == (4000, 64) and z.min() >= 0.0 and z.max() <= 1.0
    assert abs(z.mean() - 0.5) < 0.01 and abs(z.var() - 1 / 12) < 0.005  # uniform on [0, 1]


def test_an_unknown_backend_is_refused_with_the_valid_names():
    with pytest.raises(ValueError, match="unknown skill.backend 'vic'.*aps, diayn, cic"):
        make_skill_backend("vic", OBS_DIM, SKILL, CPU)


def test_a_configured_skill_size_overrides_the_backends_own():
    assert _backend("aps", skill_dim=5).sample_skills(np.random.default_rng(0), 3).shape == (3, 5)


# -- the kNN particle entropy ---------------------------------------------------------------------

def test_particle_entropy_matches_a_hand_computation():
    h = torch.tensor([[0.0], [1.0], [3.0], [6.0]])
    # k = 2 nearest within the batch, the point itself (distance 0) included, as in URLB:
    # 0 -> {0, 1}, 1 -> {0, 1}, 3 -> {0, 2}, 6 -> {0, 3}; reward log(1 + mean)
    expected = torch.log1p(torch.tensor([[0.5], [0.5], [1.0], [1.5]]))
    torch.testing.assert_close(particle_entropy(h, k=2), expected)

    # With running normalisation: distances over their running mean m (this batch's included),
    # less the clip, floored at 0.
    stats = RunningMeanStd()
    got = particle_entropy(h, k=2, stats=stats, clip=0.1)
    m = (0 * 1e-4 + 7.0) / (1e-4 + 8)  # the mean of the 8 distances 0,1,0,1,0,2,0,3 (and the prior)
    assert float(stats.mean) == pytest.approx(m)
    hand = [math.log1p(np.mean([max(d / m - 0.1, 0) for d in ds]))
            for ds in ([0, 1], [0, 1], [0, 2], [0, 3])]
    torch.testing.assert_close(got, torch.tensor(hand, dtype=torch.float32)[:, None])


def test_aps_reward_is_the_feature_skill_product_plus_beta_times_the_entropy():
    aps = _backend("aps", knn_k=3, beta=5.0, knn_clip=0.0)
    batch = _batch(aps, n=6)
    reward = aps.intrinsic_reward(batch)
    assert reward.shape == (6, 1) and not reward.requires_grad

    # by hand, in NumPy: h = phi(s') unnormalised for the entropy, normalised for phi^T z
    h = aps.features(batch.next_obs).detach().numpy().astype(np.float64)
    z = batch.skill.numpy()
    dists = np.linalg.norm(h[:, None] - h[None], axis=-1)
    knn = np.sort(dists, axis=1)[:, :3]
    m = knn.sum() / (1e-4 + knn.size)
    entropy = np.log1p((knn / m).mean(axis=1))
    sf = ((h / np.linalg.norm(h, axis=1, keepdims=True)) * z).sum(axis=1)
    np.testing.assert_allclose(reward[:, 0].numpy(), sf + 5.0 * entropy, rtol=1e-4, atol=1e-5)


def test_aps_features_are_unit_vectors_and_learn_to_point_at_the_skill():
    aps = _backend("aps")
    batch = _batch(aps, n=64)
    phi = aps.phi(batch.next_obs)
    torch.testing.assert_close(phi.norm(dim=1), torch.ones(64))

    def alignment() -> float:
        with torch.no_grad():
            return (aps.phi(batch.next_obs) * batch.skill).sum(-1).mean().item()

    before = alignment()
    losses = [aps.update(batch)["aps_loss"] for _ in range(60)]
    assert alignment() > before + 0.3
    assert losses[-1] < losses[0] and losses[-1] == pytest.approx(-alignment(), abs=0.05)


# -- DIAYN ---------------------------------------------------------------------------------------

def test_diayn_reward_is_log_q_minus_log_p():
    diayn = _backend("diayn", skill_dim=4)
    # A discriminator that ignores the state: q(z|s') = softmax(bias) = (0.1, 0.2, 0.3, 0.4).
    last = diayn.discriminator[-1]
    assert isinstance(last, nn.Linear)
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.log(torch.tensor([0.1, 0.2, 0.3, 0.4])))
    batch = _batch(diayn, n=40)
    reward = diayn.intrinsic_reward(batch)[:, 0]
    q = torch.tensor([0.1, 0.2, 0.3, 0.4])[batch.skill.argmax(1)]
    torch.testing.assert_close(reward, torch.log(q) - math.log(1 / 4))
    # the most likely skill earns log(0.4 * 4) > 0, the least likely log(0.4) < 0
    assert reward.max().item() == pytest.approx(math.log(1.6), abs=1e-5)


def test_diayn_discriminator_learns_which_skill_visits_which_states():
    diayn = _backend("diayn", skill_dim=4)
    batch = _batch(diayn, n=64)
    # skill i puts s' near 3 * e_i: the skills are distinguishable from the state
    centres = torch.zeros(4, OBS_DIM)
    centres[torch.arange(4), torch.arange(4)] = 3.0
    batch = batch._replace(next_obs=centres[batch.skill.argmax(1)] + 0.3 * batch.next_obs)
    first = diayn.update(batch)
    reward_before = diayn.intrinsic_reward(batch).mean().item()
    for _ in range(100):
        last = diayn.update(batch)
    assert last["diayn_accuracy"] == 1.0 and last["diayn_loss"] < first["diayn_loss"] / 4
    assert diayn.intrinsic_reward(batch).mean().item() > reward_before + 1.0  # towards log 4


# -- CIC -------------------------------------------------------------------------------------------

def test_cic_scores_transitions_against_skills_and_rewards_their_entropy():
    cic = _backend("cic", skill_dim=8, temperature=0.5)
    batch = _batch(cic, n=32)
    logits = cic.logits(batch)
    assert logits.shape == (32, 32)
    assert logits.abs().max().item() <= 1 / 0.5 + 1e-5  # cosine similarity over the temperature
    reward = cic.intrinsic_reward(batch)
    assert reward.shape == (32, 1) and torch.all(reward >= 0) and torch.isfinite(reward).all()

    # a transition whose displacement s' - s encodes its skill is learned to be identified
    batch = batch._replace(next_obs=batch.obs + 3 * batch.skill[:, :OBS_DIM])
    first = cic.update(batch)
    assert first["cic_loss"] == pytest.approx(math.log(32), rel=0.15)  # chance at the start
    for _ in range(100):
        last = cic.update(batch)
    # every skill picks out its own transition among the 32 (the loss floor is well above 0:
    # 32 embeddings in 8 dimensions cannot all be far apart at temperature 0.5)
    assert last["cic_accuracy"] == 1.0 and last["cic_loss"] < first["cic_loss"] - 1.5


@pytest.mark.parametrize("name", list(SKILL_BACKENDS))
def test_backend_state_round_trips(name):
    a, b = _backend(name), _backend(name, lr=0.5)
    batch = _batch(a, n=24)
    for _ in range(3):
        a.update(batch)
    a.intrinsic_reward(batch)  # moves the running statistics
    b.load_state_dict(a.state_dict())
    torch.testing.assert_close(b.intrinsic_reward(batch), a.intrinsic_reward(batch))


# -- the skill-conditioned agent ------------------------------------------------------------------

def test_the_aps_critic_is_successor_features_dotted_with_the_skill():
    torch.manual_seed(0)
    agent = SkillAgent(OBS_DIM, ACTION_DIM, 10, SAC_CFG, CPU, successor_features=True)
    aps = _backend("aps")
    batch = _batch(aps, n=8)
    q = agent.sac.critic(torch.cat([batch.obs, batch.skill], 1), batch.action)
    assert q.shape == (2, 8, 1)
    x = torch.cat([batch.obs, batch.skill, batch.action], 1)
    psi = agent.sac.critic.psi(x)  # (2, 8, 10): one successor feature per skill dimension
    torch.testing.assert_close(q[..., 0], (psi * batch.skill).sum(-1))
    torch.testing.assert_close(agent.q(batch.obs, batch.action, batch.skill),
                               q.min(dim=0).values)


def test_the_agent_acts_by_skill_and_its_updates_use_each_transitions_skill():
    torch.manual_seed(0)
    aps = _backend("aps")
    agent = SkillAgent(OBS_DIM, ACTION_DIM, aps.skill_dim, SAC_CFG, CPU, True)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=OBS_DIM).astype(np.float32)
    z = aps.sample_skills(rng, 50)
    actions = np.stack([agent.act(obs, zi, rng, deterministic=True) for zi in z])
    assert actions.shape == (50, ACTION_DIM) and np.all(np.abs(actions) < 1)
    assert np.unique(actions.round(6), axis=0).shape[0] == 50  # the skill changes the action
    # deterministic acting is the actor's tanh(mean) on [s, z]
    mean, _ = agent.sac.actor(torch.from_numpy(np.concatenate([obs, z[0]]))[None])
    np.testing.assert_allclose(actions[0], torch.tanh(mean)[0].detach().numpy(), atol=1e-6)

    buffer = SkillReplayBuffer(OBS_DIM, ACTION_DIM, aps.skill_dim, 100, CPU, seed=0)
    for i in range(60):
        o = np.full(OBS_DIM, i, np.float32)
        buffer.add(o, np.zeros(ACTION_DIM, np.float32), 0.0, 0.0, o + 1, z[i % 50])
    batch = buffer.sample(32)
    ids = batch.obs[:, 0].long().numpy()
    np.testing.assert_array_equal(batch.skill.numpy(), z[ids % 50])  # each row keeps its skill
    metrics = agent.update(batch._replace(reward=aps.intrinsic_reward(batch)))
    assert {"critic_loss", "actor_loss", "alpha"} <= set(metrics)
    assert all(math.isfinite(v) for v in metrics.values())

    state = buffer.state_dict()
    other = SkillReplayBuffer(OBS_DIM, ACTION_DIM, aps.skill_dim, 100, CPU, seed=1)
    other.load_state_dict(state)
    torch.testing.assert_close(other.skill[:60], buffer.skill[:60])

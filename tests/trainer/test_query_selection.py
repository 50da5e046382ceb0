import numpy as np
import pytest
import torch

from runvocab.config import RewardConfig
from trainer.query_selection import (
    Candidates,
    disagreement,
    entropy,
    sample_candidates,
    segment_returns,
    select_queries,
)
from trainer.reward_model import RewardModel
from trainer.trajectories import Trajectory


def _trajectory(i: int, length: int, obs_dim: int = 3, act_dim: int = 1) -> Trajectory:
    rng = np.random.default_rng(i)
    return Trajectory(
        id=i, obs=rng.normal(size=(length, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (length, act_dim)).astype(np.float32),
        true_rewards=rng.random(length).astype(np.float32),
        states=np.zeros((length, 2)), context=0, success=False,
    )


def test_candidates_pair_different_trajectories_and_fit_inside_them():
    lengths = np.array([60, 100, 55, 200])
    c = sample_candidates(lengths, 5000, 50, np.random.default_rng(0))
    assert np.all(c.traj0 != c.traj1)
    for traj, start in ((c.traj0, c.start0), (c.traj1, c.start1)):
        assert np.all(start >= 0) and np.all(start + 50 <= lengths[traj])
    # every trajectory and both ends of the longest one are reachable
    assert set(np.concatenate([c.traj0, c.traj1])) == {0, 1, 2, 3}
    assert c.start0[c.traj0 == 3].max() == 150


def test_candidates_need_two_trajectories():
    with pytest.raises(ValueError, match="two trajectories"):
        sample_candidates(np.array([100, 10]), 10, 50, np.random.default_rng(0))


def test_prefix_sum_segment_returns_equal_direct_sums():
    pool = [_trajectory(i, 80) for i in range(6)]
    model = RewardModel(3, 1, RewardConfig(hidden_dim=16, hidden_layers=2), torch.device("cpu"), 0)
    c = sample_candidates(np.array([80] * 6), 50, 20, np.random.default_rng(1))
    r0, r1 = segment_returns(model, pool, c, 20)
    for k in range(50):
        t = pool[c.traj1[k]]
        s = c.start1[k]
        x = torch.from_numpy(np.concatenate([t.obs, t.actions], 1)[s : s + 20])
        direct = model.member_rewards(x).sum(1)
        torch.testing.assert_close(r1[:, k], direct, rtol=1e-4, atol=1e-4)
    assert r0.shape == (3, 50)


def test_disagreement_picks_the_highest_spread_pair():
    # Three members' P for four pairs; pair 2 has the widest spread.
    p = torch.tensor([[0.5, 0.9, 0.1, 0.6], [0.5, 0.8, 0.9, 0.5], [0.5, 0.85, 0.5, 0.4]])
    spread = disagreement(p)
    assert int(spread.argmax()) == 2
    assert spread[0] == 0
    # entropy prefers P near 0.5 for every member
    assert int(entropy(p).argmax()) == 0


def test_select_queries_by_disagreement_on_a_constructed_ensemble():
    pool = [_trajectory(i, 50) for i in range(4)]
    model = RewardModel(3, 1, RewardConfig(hidden_dim=8, hidden_layers=1), torch.device("cpu"), 0)
    # Members agree except on observations of trajectory 3, where member 0 sees a huge reward:
    # only pairs involving trajectory 3 have spread.
    with torch.no_grad():
        for layer in model.ensemble.layers:
            layer.weight.zero_()
            layer.bias.zero_()
        model.ensemble.layers[0].bias[0, 0, 0] = 0.0
    pool[3].obs[:] = 10.0
    with torch.no_grad():
        model.ensemble.layers[0].weight[0, 0, 0] = 1.0  # member 0: hidden = obs[0]
        model.ensemble.layers[1].weight[0, 0, 0] = 1.0  # member 0: reward = tanh(obs[0])
    sel = select_queries("disagreement", model, pool, 5, 40, 10, np.random.default_rng(0))
    q = sel.queries
    assert len(q) == 5
    assert np.all((q.traj0 == 3) | (q.traj1 == 3))
    assert np.all(sel.score > 0)


def test_per_query_selection_takes_each_query_from_its_own_fresh_candidates():
    pool = [_trajectory(i, 60) for i in range(6)]
    model = RewardModel(3, 1, RewardConfig(hidden_dim=16, hidden_layers=2), torch.device("cpu"), 0)
    n, factor = 8, 10
    sel = select_queries("disagreement", model, pool, n, factor, 20, np.random.default_rng(3),
                         mode="per_query")
    # The same draw as the selection made: n groups of `factor` candidates, one per query.
    cands = sample_candidates(np.array([60] * 6), n * factor, 20, np.random.default_rng(3))
    p = torch.sigmoid(torch.stack(segment_returns(model, pool, cands, 20)).diff(dim=0)[0])
    spread = disagreement(p).view(n, factor)
    assert np.array_equal(sel.candidate // factor, np.arange(n))  # query i from group i
    assert np.array_equal(sel.candidate % factor, spread.argmax(dim=1).numpy())
    assert np.array_equal(sel.queries.traj0, cands.traj0[sel.candidate])
    # top_k ranks the whole draw instead: its picks are the n best overall.
    top = select_queries("disagreement", model, pool, n, factor, 20, np.random.default_rng(3))
    assert set(top.candidate) == set(torch.topk(spread.reshape(-1), n).indices.tolist())
    with pytest.raises(ValueError, match="valid: per_query, top_k"):
        select_queries("disagreement", model, pool, n, factor, 20, np.random.default_rng(3),
                       mode="best")


def test_uniform_selection_and_unknown_rule():
    pool = [_trajectory(i, 50) for i in range(4)]
    model = RewardModel(3, 1, RewardConfig(hidden_dim=8, hidden_layers=1), torch.device("cpu"), 0)
    sel = select_queries("uniform", model, pool, 7, 10, 10, np.random.default_rng(0))
    assert isinstance(sel.queries, Candidates) and len(sel.queries) == 7
    with pytest.raises(ValueError, match="valid: uniform, disagreement, entropy"):
        select_queries("bald", model, pool, 7, 10, 10, np.random.default_rng(0))

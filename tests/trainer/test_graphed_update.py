"""The graph-ready update (trainer/graphed_update.py) is SAC's update: on the CPU it runs its
static batch and capturable optimisers eagerly, and must give the plain update's parameters;
on a GPU (skipped without one) the replayed CUDA graphs must give the eager update's."""

from __future__ import annotations

import dataclasses
import io

import pytest
import torch

from runvocab.config import SACConfig
from trainer.sac import SAC, Batch

CFG = SACConfig(hidden_dim=32, hidden_layers=2, batch_size=16)
OBS, ACT = 5, 3


def batches(n: int, device: torch.device) -> list[Batch]:
    g = torch.Generator().manual_seed(7)
    return [Batch(*(torch.randn(16, d, generator=g).to(device) for d in (OBS, ACT, 1, OBS)))
            for _ in range(n)]


def trained(device: torch.device, graph_ready: bool, updates: list[Batch],
            reset_at: int | None = None) -> tuple[SAC, list[dict[str, float]]]:
    torch.manual_seed(0)
    agent = SAC(OBS, ACT, CFG, device, graph_ready=graph_ready)
    torch.manual_seed(1)  # the actor's noise: the same stream on both sides
    metrics = []
    for i, batch in enumerate(updates):
        if i == reset_at:
            agent.reset_critic()
        metrics.append({k: float(v) for k, v in agent.update(batch).items()})
    return agent, metrics


def assert_same_agent(a: SAC, b: SAC, tol: float) -> None:
    for name in ("actor", "critic", "critic_target"):
        for (key, p), q in zip(getattr(a, name).state_dict().items(),
                               getattr(b, name).state_dict().values(), strict=True):
            torch.testing.assert_close(p, q, rtol=tol, atol=tol, msg=f"{name}.{key}")
    torch.testing.assert_close(a.log_alpha, b.log_alpha, rtol=tol, atol=tol)
    assert a.updates == b.updates


def test_the_graph_ready_update_gives_the_plain_updates_parameters_on_the_cpu() -> None:
    cpu = torch.device("cpu")
    data = batches(9, cpu)
    plain, plain_metrics = trained(cpu, False, data, reset_at=5)
    ready, ready_metrics = trained(cpu, True, data, reset_at=5)
    assert ready.graphed is not None and plain.graphed is None
    assert ready.actor_opt.param_groups[0]["capturable"]
    assert_same_agent(plain, ready, tol=1e-5)
    for p, r in zip(plain_metrics, ready_metrics, strict=True):
        assert p.keys() == r.keys()
        assert all(abs(p[k] - r[k]) <= 1e-4 * max(1.0, abs(p[k])) for k in p)
    # The target moved on every 2nd update, the actor on every one, on both sides alike.
    assert "actor_loss" in ready_metrics[0] and "actor_loss" in ready_metrics[1]


def test_a_checkpoint_loads_into_a_graph_ready_agent_and_carries_on_alike() -> None:
    cpu = torch.device("cpu")
    data = batches(8, cpu)
    plain, _ = trained(cpu, False, data[:4])
    checkpoint = io.BytesIO()
    torch.save(plain.state_dict(), checkpoint)
    checkpoint.seek(0)
    ready = SAC(OBS, ACT, CFG, cpu, graph_ready=True)
    ready.load_state_dict(torch.load(checkpoint))
    assert ready.actor_opt.param_groups[0]["capturable"]  # as built, not as saved
    torch.manual_seed(3)
    for batch in data[4:]:
        plain.update(batch)
    torch.manual_seed(3)
    for batch in data[4:]:
        ready.update(batch)
    assert_same_agent(plain, ready, tol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_replayed_cuda_graphs_give_the_eager_updates_parameters() -> None:
    cuda = torch.device("cuda")
    cfg = dataclasses.replace(CFG, cuda_graph=True)
    # Two schedule slots (target step or not) take turns; each is warmed up 3 times, recorded
    # at its 4th update and replayed after: 10 updates record and replay both, then a critic
    # reset drops them and 12 more record and replay them again.
    data = batches(22, cuda)
    runs, recorded = [], []
    for capture in (False, True):
        torch.manual_seed(0)
        agent = SAC(OBS, ACT, cfg, cuda)
        assert agent.graphed is not None
        agent.graphed.capture = capture
        torch.manual_seed(1)
        for i, batch in enumerate(data):
            if i == 10:
                recorded.append(len(agent.graphed.graphs))
                agent.reset_critic()
                assert not agent.graphed.graphs
            agent.update(batch)
        recorded.append(len(agent.graphed.graphs))
        runs.append(agent)
    eager, graphed = runs
    assert recorded == [0, 0, 2, 2]  # eager: never recorded; graphed: both slots, twice
    assert_same_agent(eager, graphed, tol=1e-4)


def test_tf32_is_the_runs_setting_on_cuda_and_left_alone_on_the_cpu() -> None:
    before = torch.backends.cuda.matmul.allow_tf32
    SAC(OBS, ACT, dataclasses.replace(CFG, tf32=not before), torch.device("cpu"))
    assert torch.backends.cuda.matmul.allow_tf32 == before
    if not torch.cuda.is_available():
        return
    try:
        SAC(OBS, ACT, dataclasses.replace(CFG, tf32=True), torch.device("cuda"))
        assert torch.backends.cuda.matmul.allow_tf32
        SAC(OBS, ACT, CFG, torch.device("cuda"))  # a later run without it gets float32 back
        assert not torch.backends.cuda.matmul.allow_tf32
    finally:
        torch.backends.cuda.matmul.allow_tf32 = before

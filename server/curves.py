"""A run's learning curve beside its peers', as the experiment report draws it.

Peers are the runs in the database with the same task, preset and teacher error rate. Each
algorithm is one curve: the mean and standard deviation across its runs (seeds) of the
evaluation return, on the steps all of them reached (sepoa/plots.py). The run
itself is drawn alone as well, so it can be told from its group.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import Run, read_metrics
from server.services import reading


def _eps(run: Run) -> float:
    return float((run.teacher_params or {}).get("eps", 0.0))


def _series(session: Session, run_id: int, metric: str) -> tuple[list[int], list[float]]:
    rows = read_metrics(session, run_id=run_id, stream="eval")
    points = [(row.step, row.values[metric]) for row in rows
              if isinstance(row.values.get(metric), int | float)]
    return [s for s, _ in points], [float(v) for _, v in points]


def peer_curves_png(session: Session, run: Run, metric: str) -> bytes:
    """PNG of `metric` from the evaluations of `run` and its peers, one curve per algorithm."""
    from sepoa.plots import curves_png  # matplotlib: only when a figure is asked

    with reading(session):
        peers = [
            peer for peer in session.scalars(
                select(Run).where(Run.task == run.task, Run.preset == run.preset)
                .order_by(Run.id))
            if _eps(peer) == _eps(run)
        ]
    curves: dict[str, Any] = {}
    for peer in peers:
        series = _series(session, peer.id, metric)
        if series[0]:
            curves.setdefault(f"{peer.algo} ({_count(peers, peer.algo)})", []).append(series)
    own = _series(session, run.id, metric)
    if own[0]:
        curves[f"this run ({run.algo}, seed {run.seed})"] = [own]
    title = f"{run.task} · {run.preset} · ε = {_eps(run):g}"
    return curves_png(curves, title=title, ylabel=f"evaluation {metric.replace('_', ' ')}")


def _count(peers: list[Run], algo: str) -> str:
    n = sum(peer.algo == algo for peer in peers)
    return f"{n} run" if n == 1 else f"{n} runs"

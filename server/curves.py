"""A run's learning curve beside its peers', as the experiment report draws it.

Peers are the runs in the database with the same task, preset and teacher error rate. Each
algorithm is one curve: the mean and standard deviation across its runs (seeds) of the
evaluation return, on the steps all of them reached (figures/curves.py). The run
itself is drawn alone as well, so it can be told from its group.

Drawing takes a fraction of a second of the server's CPU, so figures are kept by their data:
every open run page asks again after each new evaluation, and all but the first get the PNG
drawn for the first (the data is read each time; only an unchanged figure is reused).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Callable
from functools import lru_cache

from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import Run, read_metrics
from server.services import reading

Figure = tuple[tuple[str, tuple[tuple[tuple[int, ...], tuple[float, ...]], ...]], ...]
"""per curve label, the seeds' (steps, values): hashable, so a drawn figure is kept by it"""
_drawing = threading.Lock()


def _eps(run: Run) -> float:
    return float((run.teacher_params or {}).get("eps", 0.0))


def _series(session: Session, run_id: int, metric: str) -> tuple[list[int], list[float]]:
    rows = read_metrics(session, run_id=run_id, stream="eval")
    points = [(row.step, row.values[metric]) for row in rows
              if isinstance(row.values.get(metric), int | float)]
    return [s for s, _ in points], [float(v) for _, v in points]


def peer_curves_png(session: Session, run: Run, metric: str) -> bytes:
    """PNG of `metric` from the evaluations of `run` and its peers, one curve per algorithm."""
    with reading(session):
        peers = [
            peer for peer in session.scalars(
                select(Run).where(Run.task == run.task, Run.preset == run.preset)
                .order_by(Run.id))
            if _eps(peer) == _eps(run)
        ]
    # The run is one of its peers: each series is read once.
    series = {peer.id: _series(session, peer.id, metric) for peer in peers}
    counts = Counter(peer.algo for peer in peers)
    curves: dict[str, list[tuple[list[int], list[float]]]] = {}
    for peer in peers:
        if series[peer.id][0]:
            n = counts[peer.algo]
            label = f"{peer.algo} ({n} run{'' if n == 1 else 's'})"
            curves.setdefault(label, []).append(series[peer.id])
    if series[run.id][0]:
        curves[f"this run ({run.algo}, seed {run.seed})"] = [series[run.id]]
    title = f"{run.task} · {run.preset} · ε = {_eps(run):g}"
    figure = tuple(
        (label, tuple((tuple(steps), tuple(values)) for steps, values in seeds))
        for label, seeds in curves.items()
    )
    from figures.curves import curves_png  # matplotlib: only when a figure is asked

    with _drawing:  # pages asking at once wait for one drawing, then reuse it
        return _drawn(curves_png, figure, title, f"evaluation {metric.replace('_', ' ')}")


@lru_cache(maxsize=64)
def _drawn(draw: Callable[..., bytes], figure: Figure, title: str, ylabel: str) -> bytes:
    curves = {label: [(list(steps), list(values)) for steps, values in seeds]
              for label, seeds in figure}
    return draw(curves, title=title, ylabel=ylabel)

"""A run's learning curve beside its peers', as the experiment report draws it.

Peers are the runs in the database with the same task, preset, teacher kind (human or scripted)
and teacher error rate (as the run's stored configuration says). Each algorithm is one curve:
the mean and standard deviation across its runs (seeds) of the evaluation return, on the steps
all of them reached (figures/curves.py), named with the number of runs it draws. The run itself
is drawn alone as well, so it can be told from its group.

Drawing a figure takes about a second of CPU (matplotlib), so it is done by a process of its own
at a lower priority (`server.side_process`), started at the first figure and kept: in the
server's process it held the interpreter's lock against the labellers' requests all that time.
Figures are kept by their data: every open run page asks again after each new evaluation, and
all but the first get the PNG drawn for the first (the data is read each time; only an unchanged
figure is reused). The teacher-calibration figure (`GET /api/quality/calibration.png`, asked for
by the run page whenever the run's label count changes) is drawn there too, kept by its report.
"""

from __future__ import annotations

import threading
from collections import Counter, OrderedDict
from collections.abc import Callable, Hashable
from typing import TYPE_CHECKING

from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import Run, read_metrics
from server.services import reading
from server.side_process import SideProcess

if TYPE_CHECKING:
    from labelstats.calibration import CalibrationReport

Figure = tuple[tuple[str, tuple[tuple[tuple[int, ...], tuple[float, ...]], ...]], ...]
"""per curve label, the seeds' (steps, values): hashable, so a drawn figure is kept by it"""
KEPT = 64
"""drawn figures kept, the least recently asked for dropped first"""
_drawing = threading.Lock()
_drawer = SideProcess()
"""the drawing process, started at the first figure asked for (`close` ends it)"""
_kept: OrderedDict[Hashable, bytes] = OrderedDict()


def _eps(run: Run) -> float:
    """The teacher's error rate as the run trains with it: its stored configuration says,
    whether `teacher_params` or a `config` override (`teacher.eps`) set it."""
    teacher = (run.resolved_config or {}).get("teacher")
    # A run stored without a configuration (an older one): its parameters alone.
    eps = teacher.get("eps") if isinstance(teacher, dict) else (run.teacher_params or {}).get("eps")
    try:
        return float(eps if eps is not None else 0.0)
    except (TypeError, ValueError):
        return 0.0


def _pool(run: Run) -> tuple[str, float]:
    """What a run's peers share besides task and preset: who teaches it, at what error rate."""
    return str(run.teacher), _eps(run)


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
            if _pool(peer) == _pool(run)
        ]
    # The run is one of its peers: each series is read once.
    series = {peer.id: _series(session, peer.id, metric) for peer in peers}
    counts = Counter(peer.algo for peer in peers if series[peer.id][0])  # the drawn ones
    curves: dict[str, list[tuple[list[int], list[float]]]] = {}
    for peer in peers:
        if series[peer.id][0]:
            n = counts[peer.algo]
            label = f"{peer.algo} ({n} run{'' if n == 1 else 's'})"
            curves.setdefault(label, []).append(series[peer.id])
    if series[run.id][0]:
        curves[f"this run ({run.algo}, seed {run.seed})"] = [series[run.id]]
    title = f"{run.task} · {run.preset} · {run.teacher} teacher, ε = {_eps(run):g}"
    figure = tuple(
        (label, tuple((tuple(steps), tuple(values)) for steps, values in seeds))
        for label, seeds in curves.items()
    )
    ylabel = f"evaluation {metric.replace('_', ' ')}"
    return drawn_once(("curves", figure, title, ylabel), draw, figure, title, ylabel)


def calibration_png(report: CalibrationReport, *, title: str) -> bytes:
    """PNG of a teacher-calibration report (`figures.calibration`), drawn in the drawing
    process; a report equal to one drawn before gets that PNG."""
    return drawn_once(("calibration", title, repr(report)), draw_calibration, report, title)


def drawn_once(key: Hashable, function: Callable[..., bytes], *args: object) -> bytes:
    """`function(*args)` drawn in the drawing process, or the PNG drawn before for `key` (the
    figure's data). Callers asking at once wait for one drawing, then reuse it."""
    with _drawing:
        png = _kept.get(key)
        if png is None:
            png = _kept[key] = _drawer.run(function, *args)
            if len(_kept) > KEPT:
                _kept.popitem(last=False)
        else:
            _kept.move_to_end(key)
        return png


def draw(figure: Figure, title: str, ylabel: str) -> bytes:
    """The PNG of `figure` (run in the drawing process)."""
    from figures.curves import curves_png  # matplotlib: only in the process that draws

    curves = {label: [(list(steps), list(values)) for steps, values in seeds]
              for label, seeds in figure}
    return curves_png(curves, title=title, ylabel=ylabel)


def draw_calibration(report: CalibrationReport, title: str) -> bytes:
    """The PNG of a calibration report (run in the drawing process)."""
    from figures.calibration import calibration_png as draw_report  # matplotlib: only here

    return draw_report(report, title=title)


def close() -> None:
    """End the drawing process, if one was started, and forget the figures (the server's
    shutdown)."""
    with _drawing:
        _kept.clear()
        _drawer.close()

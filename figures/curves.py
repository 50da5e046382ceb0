"""Learning-curve figures as PNG bytes, from plain NumPy data.

Light on purpose (NumPy and matplotlib's Agg canvas, no torch, no pyplot state): the report
draws its figures with it and a web process can draw the same curves for a run page.

A curve is either the seeds' raw series, `[(steps, values), ...]`, which `align` turns into a
`Band`, or a prepared `Band`. Seeds that evaluated at different steps are put on one grid: the
union of their evaluation steps between the latest first step and the earliest last step (the
range every seed covers), each seed linearly interpolated onto it. The band is the mean plus or
minus one sample standard deviation (ddof=1) across seeds; one seed draws no band.
"""

from __future__ import annotations

import io
import textwrap
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import ArrayLike

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class Band(NamedTuple):
    steps: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    """sample standard deviation across seeds (zeros for one seed)"""
    n: int
    """seeds averaged"""
    low: np.ndarray | None = None
    """the band's lower edge when it is not mean - std (an interval estimate)"""
    high: np.ndarray | None = None
    """its upper edge"""


Series = tuple[ArrayLike, ArrayLike]
Curves = Mapping[str, Sequence[Series] | Band]
"""per curve label: the seeds' (steps, values), or a prepared Band"""


def align(seeds: Sequence[Series]) -> Band:
    """Mean and sample std of the seeds on the common step grid (see the module docstring).
    Seeds with no points are left out; NaN values are dropped first."""
    clean = []
    for steps, values in seeds:
        s, v = np.asarray(steps, dtype=float), np.asarray(values, dtype=float)
        keep = np.isfinite(s) & np.isfinite(v)
        s, v = s[keep], v[keep]
        if len(s):
            order = np.argsort(s, kind="stable")
            clean.append((s[order], v[order]))
    empty = np.empty(0)
    if not clean:
        return Band(empty, empty, empty, 0)
    lo, hi = max(s[0] for s, _ in clean), min(s[-1] for s, _ in clean)
    grid = np.unique(np.concatenate([s[(s >= lo) & (s <= hi)] for s, _ in clean]))
    if not len(grid):
        return Band(empty, empty, empty, len(clean))
    values = np.stack([np.interp(grid, s, v) for s, v in clean])
    std = values.std(axis=0, ddof=1) if len(clean) > 1 else np.zeros(len(grid))
    return Band(grid, values.mean(axis=0), std, len(clean))


def _band(curve: Sequence[Series] | Band) -> Band:
    return curve if isinstance(curve, Band) else align(curve)


LEGEND_ROW_INCHES = 0.2
"""the height a row of the legend adds to the figure, so the panels keep theirs"""
FIT = 0.96
"""the share of the figure's width a title or legend may take (the rest is its margins)"""


def grid_figure(panels: Mapping[tuple[str, str], Curves], rows: Sequence[str],
                cols: Sequence[str], *, title: str = "", ylabel: str = "return",
                xlabel: str = "environment steps") -> Figure:
    """A figure of panels, `panels[(row, col)]` at that row and column (a missing one is left
    blank), one colour per curve label across all panels, one legend below. The legend takes
    as many columns, and the title as many lines, as the figure's width holds."""
    labels = list(dict.fromkeys(label for curves in panels.values() for label in curves))
    colours = {label: f"C{i % 10}" for i, label in enumerate(labels)}
    width = 1.5 + 3.6 * len(cols)
    fig = Figure(figsize=(width, 0.9 + 2.8 * len(rows)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(rows), len(cols), squeeze=False, sharex=True)
    for i, row in enumerate(rows):
        for j, col in enumerate(cols):
            ax = axes[i][j]
            ax.set_title(f"{col}, {row}" if row else col, fontsize=9)
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=8)
            if i == len(rows) - 1:
                ax.set_xlabel(xlabel, fontsize=9)
            if j == 0:
                ax.set_ylabel(ylabel, fontsize=9)
            for label, curve in panels.get((row, col), {}).items():
                band = _band(curve)
                if not len(band.steps):
                    continue
                ax.plot(band.steps, band.mean, color=colours[label], label=label, lw=1.5)
                low = band.mean - band.std if band.low is None else band.low
                high = band.mean + band.std if band.high is None else band.high
                ax.fill_between(band.steps, low, high, color=colours[label], alpha=0.2, lw=0)
    renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
    handles = [Line2D([], [], color=colours[label], label=label) for label in labels]
    for ncol in range(min(len(labels), 4), 0, -1):  # as many columns as the width holds
        legend = fig.legend(handles=handles, loc="outside lower center", ncol=ncol,
                            fontsize=9, frameon=False)
        if ncol == 1 or legend.get_window_extent(renderer).width <= FIT * fig.bbox.width:
            fig.set_size_inches(width, fig.get_figheight()
                                + LEGEND_ROW_INCHES * -(-len(labels) // ncol))
            break
        legend.remove()
    for chars in range(len(title), 0, -1):  # as few lines as the width holds
        suptitle = fig.suptitle("\n".join(textwrap.wrap(title, chars)), fontsize=11)
        if suptitle.get_window_extent(renderer).width <= FIT * fig.bbox.width:
            break
    return fig


def grid_png(panels: Mapping[tuple[str, str], Curves], rows: Sequence[str],
             cols: Sequence[str], *, title: str = "", ylabel: str = "return",
             xlabel: str = "environment steps", dpi: int = 110) -> bytes:
    """`grid_figure` as PNG bytes."""
    fig = grid_figure(panels, rows, cols, title=title, ylabel=ylabel, xlabel=xlabel)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=dpi)
    return out.getvalue()


def curves_png(curves: Curves, *, title: str = "", ylabel: str = "return",
               xlabel: str = "environment steps") -> bytes:
    """One panel of curves (a run page's): PNG bytes."""
    return grid_png({("", ""): curves}, [""], [""], title=title, ylabel=ylabel,
                    xlabel=xlabel)

"""The teacher-calibration report as files: a figure (PNG), a table (Markdown) and the numbers
(JSON), from a label export (`sepoa report --calibration FILE`) or from report data the
server made (`GET /api/quality/calibration.png`). The numbers come from
`labelstats.calibration`; this module only draws and writes them (matplotlib's Agg canvas, no
pyplot state, no torch). docs/QUALITY.md explains how to read them.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from labelstats.agreement import agreement_report
from labelstats.calibration import (
    DEFAULT_EDGES,
    REQUIRED_COLUMNS,
    Bin,
    CalibrationReport,
    Group,
    Rates,
    calibration_report,
    missing_columns,
)
from labelstats.calibration_stats import EpsFit
from labelstats.labeller_quality import LabellerQuality, labeller_quality
from rundata.export_read import ExportFileError, read_export_table

MAX_LABELLERS_DRAWN = 8
"""labellers drawn in the figure (those with the most answers); the tables list all"""


def _range(low: float, high: float | None) -> str:
    return f"≥ {low:g}" if high is None else f"{low:g}–{high:g}"


def _num(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _interval(low: float | None, high: float | None, digits: int = 2) -> str:
    if low is None:
        return ""
    return f" [{_num(low, digits)}, {'∞' if high is None else _num(high, digits)}]"


def _eps_cell(fit: EpsFit) -> str:
    """The eps interval first, then the point; a wide interval is flagged (the point then says
    little)."""
    if fit.eps is None or fit.eps_low is None:
        return "–"
    if fit.eps_high is None:  # every eps above eps_low explains the answers
        return f"≥ {fit.eps_low:.2f}, no upper bound (wide)"
    return (f"{_interval(fit.eps_low, fit.eps_high).strip()} (ε̂ {fit.eps:.2f})"
            + (" wide" if fit.wide else ""))


def _eps_text(group: Group) -> str:
    return "ε " + _eps_cell(group.fit)


def _drawn(report: CalibrationReport) -> list[Group]:
    people = sorted(report.labellers, key=lambda g: -g.rates.answers)[:MAX_LABELLERS_DRAWN]
    return sorted(people, key=lambda g: g.labeller_id or 0)


def _share(rates: Rates, key: str) -> tuple[float, float, float] | None:
    """(value, low, high) of `key`: "match" (the match ratio) or "cant_tell" (its rate)."""
    value = rates.match_ratio if key == "match" else rates.cant_tell_rate
    low, high = ((rates.match_low, rates.match_high) if key == "match"
                 else (rates.cant_tell_low, rates.cant_tell_high))
    if value is None or low is None or high is None:
        return None
    return value, low, high


def _ratio_panel(ax: Any, report: CalibrationReport, key: str, title: str) -> None:
    """One panel: `key` ("match" or "cant_tell") per gap bin, a line per labeller and
    everyone's with its interval."""
    bins = report.everyone.bins
    xs = list(range(len(bins)))
    for i, group in enumerate(_drawn(report)):
        points = [(x, share[0]) for x, b in zip(xs, group.bins, strict=True)
                  if (share := _share(b.rates, key)) is not None]
        if points:
            ax.plot(*zip(*points, strict=True), marker="o", ms=3, lw=1, color=f"C{i % 10}",
                    label=f"{group.name} · {_eps_text(group)} · n {group.rates.answers}")
    everyone = [(x, share) for x, b in zip(xs, bins, strict=True)
                if (share := _share(b.rates, key)) is not None]
    if everyone:
        ax.errorbar([x for x, _ in everyone], [v for _, (v, _, _) in everyone],
                    yerr=[[max(0.0, v - lo) for _, (v, lo, _) in everyone],
                          [max(0.0, hi - v) for _, (v, _, hi) in everyone]],
                    color="black", lw=2, marker="o", ms=4, capsize=3,
                    label=f"everyone · {_eps_text(report.everyone)} · n "
                    f"{report.everyone.rates.answers}")
        fitted = [(x, b.fitted_match) for x, b in zip(xs, bins, strict=True)
                  if b.fitted_match is not None]
        if key == "match" and fitted:
            ax.plot(*zip(*fitted, strict=True), color="black", ls="--", lw=1,
                    label="everyone's fitted noisy teacher")
    ax.set_xticks(xs, [_range(b.low, b.high) for b in bins], rotation=45, ha="right",
                  fontsize=7)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("true return gap of the two trajectories / R_avg", fontsize=9)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=8)


def _algo_panel(ax: Any, report: CalibrationReport) -> None:
    algos = [(a, share) for a in report.algos if (share := _share(a.rates, "match"))]
    xs = list(range(len(algos)))
    ax.bar(xs, [v for _, (v, _, _) in algos], width=0.6,
           yerr=[[max(0.0, v - lo) for _, (v, lo, _) in algos],
                 [max(0.0, hi - v) for _, (v, _, hi) in algos]],
           capsize=3, color=[f"C{i % 10}" for i in xs])
    ax.set_xticks(xs, [f"{a.algo}\n{a.rates.answers} answers" for a, _ in algos], fontsize=8)
    ax.set_xlim(-0.8, max(len(algos), 2) - 0.2)
    ax.set_ylim(0, 1.02)
    ax.axhline(0.5, color="grey", lw=0.8, ls=":")
    ax.set_title("Queries answered correctly, per algorithm", fontsize=10)
    ax.grid(alpha=0.3, axis="y")
    ax.tick_params(labelsize=8)


def calibration_png(report: CalibrationReport, *, title: str = "", dpi: int = 110) -> bytes:
    """The report's figure: match ratio and can't-tell rate against the normalised gap (each
    labeller, and everyone with intervals and the fitted teacher), and the share answered
    correctly per algorithm; PNG bytes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    panels = 3 if report.algos else 2
    fig = Figure(figsize=(4.2 * panels, 4.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, panels, squeeze=False)[0]
    if report.everyone.rates.answers == 0:
        for ax in axes:
            ax.set_axis_off()
        axes[0].text(0.0, 0.5, "no labels yet", fontsize=12, transform=axes[0].transAxes)
    else:
        _ratio_panel(axes[0], report, "match", "Match ratio with the ground truth")
        axes[0].set_ylabel("share", fontsize=9)
        _ratio_panel(axes[1], report, "cant_tell", "Can't-tell rate")
        if report.algos:
            _algo_panel(axes[2], report)
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncol=2, fontsize=8,
                   frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    out = io.BytesIO()
    fig.savefig(out, format="png", dpi=dpi)
    return out.getvalue()


def report_dict(report: CalibrationReport) -> dict[str, Any]:
    """The report as JSON-ready data (the REST endpoint's body)."""
    return dataclasses.asdict(report)


def _rates_cells(rates: Rates) -> str:
    """answers | match ratio [interval] | can't-tell rate"""
    return (f"{rates.answers} | {_num(rates.match_ratio)}"
            f"{_interval(rates.match_low, rates.match_high)} | {_num(rates.cant_tell_rate)}")


def _group_row(group: Group) -> str:
    fit, pos = group.fit, group.position
    return (
        f"| {group.name} | {_rates_cells(group.rates)} | "
        f"{_eps_cell(fit)} | {_num(fit.lapse)} | "
        f"{_num(fit.log_likelihood, 1)} | {_num(pos.left_share)}"
        f"{_interval(pos.left_low, pos.left_high)} | {pos.p_value:.3g} |"
    )


def _bin_row(b: Bin) -> str:
    return (
        f"| {_range(b.low, b.high)} | {_rates_cells(b.rates)}"
        f"{_interval(b.rates.cant_tell_low, b.rates.cant_tell_high)} | "
        f"{_num(b.fitted_match)} |"
    )


def report_markdown(report: CalibrationReport, *, source: str) -> str:
    """The report's tables as Markdown."""
    pct = f"{report.level:.0%}"
    lines = [
        "# Teacher-calibration report",
        "",
        f"From {source}: {report.rows} labels of {len(report.runs)} run(s)"
        + (f", {report.without_truth} without ground truth left out" if report.without_truth
           else "")
        + (f", {report.gold_answers} gold or practice answers left out" if report.gold_answers
           else "") + f". Intervals at {pct}; how to read them: docs/QUALITY.md.",
        "",
        "## Per labeller",
        "",
        "| labeller | answers | match ratio | can't tell | ε | lapse | log-lik. | left share "
        "| p (left = 0.5) |",
        "|---|---|---|---|---|---|---|---|---|",
        *(_group_row(g) for g in [*report.labellers, report.everyone]),
        "",
        "## Everyone, by normalised gap",
        "",
        "| gap / R_avg | answers | match ratio | can't-tell rate | fitted teacher |",
        "|---|---|---|---|---|",
        *(_bin_row(b) for b in report.everyone.bins),
        "",
        "## Per algorithm",
        "",
        "| algorithm | runs | queries | answers | answered correctly | can't tell "
        "| median gap |",
        "|---|---|---|---|---|---|---|",
        *(f"| {a.algo} | {a.runs} | {a.queries} | {_rates_cells(a.rates)} | "
          f"{_num(a.median_gap)} |" for a in report.algos),
        "",
    ]
    return "\n".join(lines)


def _lacks(path: str, where: str, missing: list[str]) -> ExportFileError:
    needed = ", ".join(REQUIRED_COLUMNS)
    source = "a label export from `sepoa export`, docs/EXPORT.md"
    if len(missing) == len(REQUIRED_COLUMNS):
        return ExportFileError(f"{path}{where} has none of the columns a calibration report "
                               f"needs ({needed}): give {source}")
    return ExportFileError(f"{path}{where} lacks the columns a calibration report needs: "
                           f"{', '.join(missing)} (it needs {needed}: {source})")


def read_calibration_rows(path: str) -> list[dict[str, Any]]:
    """The rows of the label export at `path` (none for an export with no rows: a header
    with the columns, or an empty JSONL file, which has no header); ExportFileError for a file
    that cannot be read, or whose header or any row lacks the columns a report needs."""
    columns, rows = read_export_table(path)
    if columns and (missing := missing_columns(columns)):
        raise _lacks(path, "", missing)
    for number, row in enumerate(rows, start=1):
        if missing := missing_columns(row):
            raise _lacks(path, f" row {number}", missing)
    return rows


def default_folder(path: str) -> Path:
    """Where `sepoa report --calibration FILE` writes by default: `FILE` without its suffix,
    plus `-calibration`."""
    return Path(os.path.splitext(path)[0] + "-calibration")


def write_calibration_report(
    rows: Sequence[dict[str, Any]], folder: Path, *, source: str,
    edges: Sequence[float] = DEFAULT_EDGES,
) -> list[Path]:
    """Write calibration.png, .md and .json of `rows` (from `source`, a file name) into
    `folder`, with each labeller's quality (labellers.csv, `labelstats.labeller_quality`) and the
    agreement between labellers (agreement.json); the files written."""
    report = calibration_report(rows, edges=edges)
    folder.mkdir(parents=True, exist_ok=True)
    files = [folder / "calibration.png", folder / "calibration.md", folder / "calibration.json",
             folder / "labellers.csv", folder / "agreement.json"]
    files[0].write_bytes(calibration_png(report, title=f"Teacher calibration · {source}"))
    files[1].write_text(report_markdown(report, source=f"`{source}`"))
    files[2].write_text(json.dumps(report_dict(report), indent=1, allow_nan=False) + "\n")
    files[3].write_text(labellers_csv(labeller_quality(rows)))
    agreement = dataclasses.asdict(agreement_report(rows))
    files[4].write_text(json.dumps(agreement, indent=1, allow_nan=False) + "\n")
    return files


def labellers_csv(qualities: Sequence[LabellerQuality]) -> str:
    """One row per labeller; a share's columns are `<name>_k`, `_n`, `_rate`, `_low`, `_high`."""
    flat = []
    for quality in qualities:
        row: dict[str, Any] = {}
        for name, value in dataclasses.asdict(quality).items():
            if isinstance(value, dict):
                row |= {f"{name}_{key}": part for key, part in value.items()}
            else:
                row[name] = value
        flat.append(row)
    out = io.StringIO()
    if flat:
        writer = csv.DictWriter(out, fieldnames=list(flat[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(flat)
    return out.getvalue()

"""Where a run's wall time went: the loop's phase seconds (`seconds_<phase>` in episodes.csv,
trainer/phase_clock.py) summed over its episode rows, as seconds and shares of the wall time.

    .venv/bin/python benchmarks/run_profile.py RUN_DIR [RUN_DIR ...]
    .venv/bin/python benchmarks/run_profile.py RUN_DIR --from-step 40000   # a window of the run

Rows written before the loop timed its phases are left out (the first column says how many
steps the profile covers). "other" is the loop's own bookkeeping: the wall time no phase holds.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from trainer.phase_clock import PHASES  # noqa: E402


def profile(run_dir: str, from_step: int = 0) -> tuple[int, dict[str, float]]:
    """(steps covered, seconds per phase plus "other" and "total") of one run's episodes.csv."""
    path = os.path.join(run_dir, "episodes.csv")
    if not os.path.exists(path):
        raise SystemExit(f"error: {run_dir} holds no episodes.csv")
    totals = dict.fromkeys((*PHASES, "other", "total"), 0.0)
    steps, previous = 0, None
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            step = int(row["step"])
            timed = row.get("seconds_total") not in (None, "")
            if timed and step > from_step and previous is not None:
                steps += step - previous
                phases = {p: float(row[f"seconds_{p}"]) for p in PHASES}
                for p, s in phases.items():
                    totals[p] += s
                totals["total"] += float(row["seconds_total"])
                totals["other"] += float(row["seconds_total"]) - sum(phases.values())
            previous = step
    return steps, totals


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR")
    parser.add_argument("--from-step", type=int, default=0,
                        help="only episodes ending after this step")
    args = parser.parse_args()
    for run_dir in args.runs:
        steps, totals = profile(run_dir, args.from_step)
        if not totals["total"]:
            print(f"{run_dir}: no timed episode rows")
            continue
        total = totals["total"]
        print(f"{run_dir}: {steps} steps in {total:.0f} s ({steps / total:.1f} steps/s)")
        for phase in (*PHASES, "other"):
            print(f"  {phase:16s} {totals[phase]:9.1f} s  {totals[phase] / total:6.1%}")
        outside = total - totals["updates"]
        print(f"  {'not the update':16s} {outside:9.1f} s  {outside / total:6.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

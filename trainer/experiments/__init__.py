"""Experiments: a TOML spec describes a grid of runs (`spec.py`), the runner trains them as
separate resumable processes (`runner.py`), and the report turns a results folder into tables
and figures (`results.py`, `plots.py`, `report.py`). See docs/EXPERIMENTS.md.

Nothing here imports torch at import time: `plots` is meant to be importable by a light process.
"""

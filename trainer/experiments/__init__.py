"""Experiments: a TOML spec describes a grid of runs (`spec.py`), the runner trains them as
separate resumable processes (`runner.py`), and the report turns a results folder into tables
and figures (`results.py`, `report.py`, drawing with `sepoa/plots.py`, which the web server
shares). See docs/EXPERIMENTS.md.
"""

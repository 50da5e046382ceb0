"""Experiments: a TOML spec describes a grid of runs (`spec.py`); `sepoa experiment run` puts
the grid in the queue database, one run per grid key (`queue.py`), and trains it with local
workers or leaves it to workers elsewhere (`launch.py`, `slurm.py`); the report turns a results
folder into tables and figures (`results.py`, `tables.py`, `report.py`, `proposition.py`,
drawing with `figures.curves`, which the web server shares). See docs/EXPERIMENTS.md.
"""

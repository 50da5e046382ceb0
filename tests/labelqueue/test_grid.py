"""A grid's runs, found by their keys' prefix (`<spec name>/`): exactly that prefix, on SQLite
(whose LIKE ignores case) as on PostgreSQL, so specs named alike never see each other's runs."""

from __future__ import annotations

from sqlalchemy.orm import Session

from labelqueue import enqueue_grid_run, grid_runs

NAMES = ("grid_a", "Grid_a", "grid-a", "gridXa", "grid%a", "grid_a2")


def test_a_grid_sees_only_the_runs_of_its_own_spec_name(session: Session) -> None:
    for name in NAMES:
        enqueue_grid_run(session, grid_key=f"{name}/dmc-cheetah_run/PEBBLE/s0", name=name,
                         task="dmc:cheetah_run", algo="pebble", budget=100)
    for name in NAMES:
        assert list(grid_runs(session, prefix=f"{name}/")) == \
            [f"{name}/dmc-cheetah_run/PEBBLE/s0"], name
    assert grid_runs(session, prefix="GRID_A/") == {}

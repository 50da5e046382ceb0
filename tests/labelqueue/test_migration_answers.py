"""Upgrading a database whose labels kept `preferred` gives every stored label its answer, from
the click and the sides it was given with; the retired `gold` label source becomes `human`."""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine, inspect, text

from labelqueue import migrate
from labelqueue.schema import alembic_config

NOW = "2026-11-20 10:00:00.000000"
# (choice, left_is_first, preferred as it was stored, source) -> the answer after the upgrade
ROWS = [
    ("left", True, "first", "human", "first"),
    ("left", False, "second", "human", "second"),
    ("right", True, "second", "scripted", "second"),
    ("right", False, "first", "human", "first"),
    ("equal", True, "equal", "human", "equal"),
    ("cant_tell", False, None, "human", "cant_tell"),
    ("skip", True, None, "gold", "skip"),
]


def before_answers(url: str) -> str:
    """The revision the answers migration (0007_answers_gold_pauses) upgrades from."""
    script = ScriptDirectory.from_config(alembic_config(url))
    [revision] = [r for r in script.walk_revisions()
                  if Path(r.path).stem.endswith("answers_gold_pauses")]
    down = revision.down_revision
    assert isinstance(down, str)
    return down


def test_the_upgrade_fills_each_labels_answer_from_its_click(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'queue.db'}"
    command.upgrade(alembic_config(url), before_answers(url))
    engine = create_engine(url)
    assert "preferred" in {c["name"] for c in inspect(engine).get_columns("labels")}
    with engine.begin() as db:
        db.execute(text(
            "INSERT INTO labellers (id, name, role, token_hash, active, created_at) "
            "VALUES (1, 'ann', 'labeller', '', 1, :now)"), {"now": NOW})
        db.execute(text(
            "INSERT INTO runs (id, name, task, algo, preset, seed, config, teacher, "
            "teacher_params, budget, labels_used, step, progress, status, created_at) "
            "VALUES (1, 'r', 'dmc:cheetah_run', 'pebble', 'small', 0, '{}', 'human', '{}', "
            "100, 7, 0, '{}', 'running', :now)"), {"now": NOW})
        for i, (choice, left_is_first, preferred, source, _) in enumerate(ROWS, start=1):
            db.execute(text(
                "INSERT INTO queries (id, run_id, round, position, segment_length, "
                "first_trajectory, first_start, first_segment_return, first_trajectory_return, "
                "second_trajectory, second_start, second_segment_return, "
                "second_trajectory_return, needs_labels, label_count, status, created_at) "
                "VALUES (:id, 1, 0, :id, 50, 0, 0, 1.0, 10.0, 1, 0, 2.0, 20.0, 1, 1, "
                "'labelled', :now)"), {"id": i, "now": NOW})
            db.execute(text(
                "INSERT INTO labels (id, query_id, run_id, labeller_id, choice, left_is_first, "
                "preferred, source, answered_at) "
                "VALUES (:id, :id, 1, 1, :choice, :lif, :preferred, :source, :now)"),
                {"id": i, "choice": choice, "lif": left_is_first, "preferred": preferred,
                 "source": source, "now": NOW})
    engine.dispose()

    migrate(url)

    engine = create_engine(url)
    columns = {c["name"] for c in inspect(engine).get_columns("labels")}
    assert "answer" in columns and "preferred" not in columns
    with engine.connect() as db:
        stored = db.execute(text(
            "SELECT choice, left_is_first, answer, source FROM labels ORDER BY id")).all()
        gold = db.execute(text("SELECT gold FROM queries ORDER BY id")).scalars().all()
        used = db.execute(text("SELECT labels_used FROM runs")).scalar()
    engine.dispose()
    assert [(c, bool(lif), a) for c, lif, a, _ in stored] == [
        (c, lif, answer) for c, lif, _, _, answer in ROWS]
    assert [s for *_, s in stored] == ["human"] * 2 + ["scripted"] + ["human"] * 4
    assert gold == [False] * len(ROWS) and used == 7  # nothing else changed

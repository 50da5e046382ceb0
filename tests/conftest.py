import os
import shutil
import sqlite3
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

import pytest

# Off-screen rendering through EGL (a GPU's, or Mesa's on CPU), before anything imports MuJoCo.
os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(scope="session", autouse=True)
def migrated_sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A new SQLite queue database starts as a copy of one the real migrations built once this
    session; `upgrade head` then finds it current and checks it (15 ms instead of the 0.35 s
    that building it takes, in some 500 tests). Existing files, other databases and other
    targets (the migration tests' up- and downgrades) go the usual way, as do subprocesses."""
    from alembic import command

    from labelqueue.schema import alembic_config, sqlite_file

    built = tmp_path_factory.mktemp("migrated") / "built.db"
    command.upgrade(alembic_config(f"sqlite:///{built}"), "head")
    template = built.with_name("template.db")
    with closing(sqlite3.connect(built)) as source, closing(sqlite3.connect(template)) as copy:
        source.backup(copy)  # one self-contained file, whatever the journal held
    upgrade = command.upgrade

    def upgrade_from_template(config: Any, revision: str, **kwargs: Any) -> None:
        path = sqlite_file(config.attributes.get("url", ""))
        if revision == "head" and path is not None and not os.path.exists(path):
            try:
                os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
                shutil.copyfile(template, path)
            except OSError:  # a folder the test made unwritable: the real path says so
                pass
        upgrade(config, revision, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(command, "upgrade", upgrade_from_template)
        yield template


@pytest.fixture
def secret_returns() -> dict[str, float]:
    """The hidden ground truth pushed with the tests' pairs (`hidden_truth.SECRET_RETURNS`)."""
    from hidden_truth import SECRET_RETURNS

    return dict(SECRET_RETURNS)

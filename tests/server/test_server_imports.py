"""The web process stays light: the server never imports the trainer or torch, and the trainer
never imports the server."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def imported_packages(path: Path) -> set[str]:
    """The top-level packages a module imports anywhere in it (absolute imports)."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return {name.split(".")[0] for name in names}


def test_the_server_imports_neither_the_trainer_nor_torch() -> None:
    probe = (
        "import sys, server.app; server.app.create_app; "
        "print(sorted(m for m in sys.modules if m in ('torch', 'matplotlib')"
        " or m.split('.')[0] == 'trainer'))"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert result.stdout.strip() == "[]"
    # Nor does any server module later, e.g. when drawing a figure (sepoa.plots is shared).
    for path in (ROOT / "server").rglob("*.py"):
        assert not imported_packages(path) & {"trainer", "torch"}, path


def test_the_trainer_never_imports_the_server() -> None:
    probe = (
        "import sys, trainer; print(sorted(m for m in sys.modules if m.split('.')[0] == 'server'))"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert result.stdout.strip() == "[]"
    # Every module, without importing torch: no `import server` / `from server` anywhere.
    for path in (ROOT / "trainer").rglob("*.py"):
        assert "server" not in imported_packages(path), path

"""The house's shape: packages import only the floors below them, no two modules import each
other even lazily, the web process stays light (the server never imports the trainer or torch,
and the trainer never imports the server), and no module, Python or the pages' JavaScript, grows
past MAX_LINES unlisted."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


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
    # Nor does any server module later, e.g. when drawing a figure (figures is shared); nor
    # does it reach up into the command line's layers.
    for path in (ROOT / "server").rglob("*.py"):
        assert not imported_packages(path) & {"trainer", "torch", "experiments", "sepoa"}, path


# Who may import whom, by top-level package: a package imports only those listed for it (and
# third-party code). runvocab is the bottom; the queue package and the label statistics sit on
# it, beside each other; on the queue sit, beside each other, a run's data files (rundata) and
# what only the server asks of the queue: crowd studies (crowdstudy), external runs
# (externalruns) and the pages' read-only views (runviews); figures draws for the server and the
# reports; the trainer and the server sit beside each other; experiments and the `sepoa` command
# line are on top.
SERVER_ONLY = {"crowdstudy", "externalruns", "runviews"}
LAYERS = {
    "runvocab": set(),
    "labelqueue": {"runvocab"},
    "labelstats": {"runvocab"},
    "rundata": {"runvocab", "labelqueue"},
    **{package: {"runvocab", "labelqueue"} for package in SERVER_ONLY},
    "figures": {"runvocab", "labelqueue", "labelstats", "rundata"},
    "server": {"runvocab", "labelqueue", "labelstats", "rundata", "figures"} | SERVER_ONLY,
    "trainer": {"runvocab", "labelqueue", "rundata"},
    "experiments": {"runvocab", "labelqueue", "labelstats", "rundata", "figures", "trainer"},
    "sepoa": {"runvocab", "labelqueue", "labelstats", "rundata", "figures", "trainer", "server",
              "experiments"} | SERVER_ONLY,
}


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_each_package_imports_only_the_layers_below_it(package: str) -> None:
    others = set(LAYERS) - LAYERS[package] - {package}
    for path in (ROOT / package).rglob("*.py"):
        wrong = imported_packages(path) & others
        assert not wrong, f"{path.relative_to(ROOT)} imports {sorted(wrong)}"


def test_the_label_statistics_need_no_database_numpy_or_torch() -> None:
    probe = ("import sys, labelstats.calibration, labelstats.labeller_quality, "
             "labelstats.agreement; print(sorted(m for m in sys.modules if m.split('.')[0] in "
             "('torch', 'numpy', 'sqlalchemy', 'labelqueue')))")
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert result.stdout.strip() == "[]"


def test_figures_draw_without_torch_or_the_trainer() -> None:
    probe = ("import sys, figures.curves, figures.calibration; print(sorted(m for m in "
             "sys.modules if m == 'torch' or m.split('.')[0] in ('trainer', 'server')))")
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, cwd=ROOT
    )
    assert result.stdout.strip() == "[]"


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


def project_modules() -> dict[str, Path]:
    modules = {}
    for package in LAYERS:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def imported_modules(path: Path, modules: dict[str, Path]) -> set[str]:
    """The project's modules a module imports anywhere in it, lazy imports included: `from p
    import m` names the submodule p.m where there is one, else the package p."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            named = {f"{node.module}.{alias.name}" for alias in node.names}
            found |= named & modules.keys()
            if not named <= modules.keys():  # a name defined in the module itself
                found.add(node.module)
    return found & modules.keys()


def test_no_two_modules_import_each_other_even_lazily() -> None:
    """A module imported from inside a function still ties the two: one of them should not
    know the other (what trainer/graphed_update.py and trainer/reward_file.py are for)."""
    modules = project_modules()
    imports = {name: imported_modules(path, modules) - {name} for name, path in modules.items()}
    for start in imports:  # a depth-first search from each module, back to itself
        stack, seen = [(start, [start])], set()
        while stack:
            name, trail = stack.pop()
            for after in imports[name]:
                assert after != start, "import cycle: " + " -> ".join([*trail, start])
                if after not in seen:
                    seen.add(after)
                    stack.append((after, [*trail, after]))


# A module longer than this holds more than one idea, or is about to: split it at its seam. A
# file may pass it only when listed here with the reason. The pages' ES modules (web/static)
# are held to it as the packages' Python modules are.
MAX_LINES = 600
LONG_MODULES: dict[str, str] = {}


def measured_modules() -> list[Path]:
    """The product's modules the size limit holds: every package's Python and the pages' JS."""
    paths = [path for package in LAYERS for path in (ROOT / package).rglob("*.py")]
    return paths + sorted((ROOT / "web" / "static").glob("*.js"))


def test_no_module_grows_past_the_limit_unlisted() -> None:
    assert any(path.suffix == ".js" for path in measured_modules()), "the pages' JS is measured"
    long = {}
    for path in measured_modules():
        lines = len(path.read_text().splitlines())
        name = str(path.relative_to(ROOT))
        if lines > MAX_LINES and name not in LONG_MODULES:
            long[name] = lines
    assert not long, f"over {MAX_LINES} lines, split them or list them with a reason: {long}"
    stale = [name for name in LONG_MODULES
             if len((ROOT / name).read_text().splitlines()) <= MAX_LINES]
    assert not stale, f"listed as long but no longer are: {stale}; take them off LONG_MODULES"


# The queue package holds the tables and the atomic operations on them, and no more: what only
# the server asks of it lives on the floor above (SERVER_ONLY, rundata). Past this, move the
# newest feature out, at its seam.
QUEUE_MAX_LINES = 5000


def test_the_queue_package_stays_tables_and_atomic_operations() -> None:
    lines = sum(len(path.read_text().splitlines()) for path in (ROOT / "labelqueue").glob("*.py"))
    assert lines < QUEUE_MAX_LINES, (
        f"labelqueue has {lines} lines (at most {QUEUE_MAX_LINES}): move what only the server "
        "uses to a package above it")

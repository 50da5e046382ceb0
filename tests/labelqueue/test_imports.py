"""The server imports the queue package and must stay light: no trainer, no torch."""

from __future__ import annotations

import subprocess
import sys


def test_importing_labelqueue_pulls_in_neither_the_trainer_nor_torch() -> None:
    probe = (
        "import sys, labelqueue; print(sorted({'torch', 'trainer', 'numpy'} & set(sys.modules)))"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "[]"

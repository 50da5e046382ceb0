"""What docs/SEPOA.md states that tests hold the code to."""

from __future__ import annotations

import tomllib
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs" / "SEPOA.md"


def authors_overrides() -> dict:
    """The overrides under "S-EPOA as the authors run it": its toml block, parsed."""
    section = DOCS.read_text().split("## S-EPOA as the authors run it")[1]
    return tomllib.loads(section.split("```toml")[1].split("```")[0])

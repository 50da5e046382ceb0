"""Text a person gives that must say something (a labeller's name, a run's name or task, an
invite's note): one rule for the API's schemas, the queue's operations and the command line."""

from __future__ import annotations

import re

VISIBLE_CHAR = r"[^\x00-\x20\x85\xa0\u1680\u2000-\u200a\u2028\u2029\u202f\u205f\u3000]"
"""a character besides white space (and control characters)"""
BLANK = "is blank: give some text besides white space"


def filled(text: str, what: str = "") -> str:
    """`text` without its outer white space; ValueError (`what` then `BLANK`) when nothing
    else is left."""
    if not re.search(VISIBLE_CHAR, text):
        raise ValueError(f"{what} {BLANK}".lstrip())
    return text.strip()

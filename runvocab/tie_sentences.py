"""The tie sentence that ends every task's instruction (`runvocab.instructions`): what a
labeller should answer when two clips are equally good, one of three kinds (`tie_kind`), chosen
from what the task's reward does and checked against it (`trainer.tie_check`)."""

from __future__ import annotations

OFTEN_SHARE = 0.5
"""a tie sentence says ties are common early on ("often") when at least this share of the pairs
of random-action segments have exactly equal returns (`trainer.tie_check`)"""
RARE_SHARE = 0.01
"""a tie sentence says exact ties are rare when fewer than this share of pairs tie, with random
actions and with none"""

# The kinds (tests/trainer/test_tie_check.py checks each task's against its reward):
# "often" and "sometimes" name what makes both clips score nothing (the reward is exactly 0
# then, so the scripted teacher, and the truth a labeller is scored against, says "equal");
# "rare" where the reward never stops telling two clips apart.
OFTEN_TAIL = " Early in training most pairs are like that."
RARE = ("Two clips are hardly ever exactly as good as each other: if they look alike, prefer "
         "the one that is even slightly better.")


def ties(condition: str, often: bool = False) -> str:
    """The tie sentence of a reward that is exactly 0 unless `condition` holds."""
    return f"If neither clip {condition}, they are equally good." + (OFTEN_TAIL if often else "")


# Shared endings, so that every task says what to do when a clip shows nothing of the goal.
NEITHER = ties("gets there")
CLOSER = "If neither finishes, prefer the one that gets closer to finishing."

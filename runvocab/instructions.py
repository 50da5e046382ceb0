"""What a labeller is told "better" means, per task: the goal in one line, then what decides
between two clips, in order. Written from each task's reward (dm_control's suite sources,
Metaworld v3's `compute_reward`), so that people prefer what the reward prefers.

A run shows its own instruction when an operator gave one (`runs.instruction`), else
`default_instruction(task)`: its own text for a known task (`instructions_dmc`,
`instructions_metaworld`), or a generic one built from the task's name. Data only: no torch, no
MuJoCo (the server imports it).
"""

from __future__ import annotations

import hashlib

from runvocab.instructions_dmc import DMC
from runvocab.instructions_metaworld import METAWORLD
from runvocab.tie_sentences import NEITHER, OFTEN_TAIL, RARE

MAX_CHARS = 2000
"""the longest instruction an operator may store"""

_BY_FAMILY = {"dmc": DMC, "metaworld": METAWORLD}


def specific_instruction(task: str) -> str | None:
    """The task's own instruction ("goal" line, then what decides), or None for a task
    without one."""
    family, _, name = task.partition(":")
    entry = _BY_FAMILY.get(family, {}).get(name)
    return None if entry is None else f"{entry[0]}\n{entry[1]}"


def tie_sentence(task: str) -> str:
    """The last sentence of the task's own (or generic) instruction: what ties look like."""
    text = default_instruction(task)
    for kind_end in (OFTEN_TAIL, ):
        if text.endswith(kind_end):
            body = text[:-len(kind_end)]
            return body[body.rindex("If neither"):] + kind_end
    if text.endswith(RARE):
        return RARE
    return text[text.rindex("If neither"):] if "If neither" in text else ""


def tie_kind(task: str) -> str:
    """What the task's instruction says of exact ties: "often" (most early pairs), "sometimes"
    (when neither clip does what the reward pays for) or "rare"; "" when it says nothing."""
    sentence = tie_sentence(task)
    if sentence.endswith(OFTEN_TAIL):
        return "often"
    if sentence == RARE:
        return "rare"
    return "sometimes" if sentence.endswith("they are equally good.") else ""


def generic_instruction(task: str) -> str:
    """An instruction built from the task's name alone, for a task without its own."""
    name = task.partition(":")[2] or task
    words = name.replace("_", " ").replace("-", " ").strip() or "the task"
    return (f"Do the task “{words}” as well as possible.\n"
            "Prefer the clip that gets nearer to doing it, or does it for longer. "
            f"{NEITHER}")


def default_instruction(task: str) -> str:
    """What a run of `task` shows when its operator gave no instruction of its own."""
    return specific_instruction(task) or generic_instruction(task)


def run_instruction(task: str, override: str | None) -> str:
    """The instruction a run shows: the operator's text when there is one, else the task's."""
    text = (override or "").strip()
    return text or default_instruction(task)


def clean_instruction(text: str) -> str:
    """An operator's instruction as stored: line ends normalised, outer blanks stripped;
    ValueError naming the problem when it is empty, too long or holds control characters."""
    text = text.replace("\r\n", "\n").replace("\r", "\n").strip()
    if not text:
        raise ValueError("is empty; leave it out (or null) to use the task's own instruction")
    if len(text) > MAX_CHARS:
        raise ValueError(f"is {len(text)} characters long; at most {MAX_CHARS} are stored")
    bad = sorted({f"U+{ord(c):04X}" for c in text if ord(c) < 32 and c not in "\n\t"})
    if bad:
        raise ValueError(f"holds control characters ({', '.join(bad)})")
    return text


def instruction_sha256(text: str) -> str:
    """The hex sha256 of an instruction's UTF-8 text: the same text, the same hash."""
    return hashlib.sha256(text.encode()).hexdigest()

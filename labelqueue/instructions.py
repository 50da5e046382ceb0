"""A run's instruction to labellers: the operator's own text, or the task's default.

`runs.instruction` holds the operator's text (none: the task's own, `runvocab.instructions`).
Every time a run's instruction is set, at creation too, its full text is appended to
`run_instructions` with the time: the export gives each label the text that was in force when it
was answered, even after later edits (`instructions_at`).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue.errors import Invalid
from labelqueue.models import Run, RunInstruction, utcnow
from labelqueue.transaction import detach, get_row, transaction
from runvocab.instructions import clean_instruction, instruction_sha256, run_instruction


def checked_instruction(instruction: str | None) -> str | None:
    """The operator's text as stored (None: the task's own); Invalid naming the problem."""
    if instruction is None:
        return None
    try:
        return clean_instruction(instruction)
    except ValueError as err:
        raise Invalid(f"instruction {err}") from None



def record_instruction(session: Session, run: Run) -> None:
    """Appends the run's instruction as it reads now to its history (inside the caller's
    transaction; the run has its id)."""
    text = run_instruction(run.task, run.instruction)
    session.add(RunInstruction(run_id=run.id, text=text, sha256=instruction_sha256(text),
                               custom=run.instruction is not None, set_at=utcnow()))


def set_instruction(session: Session, *, run_id: int, instruction: str | None) -> Run:
    """The run's instruction from now on: the operator's text, or None for the task's own.
    NotFound for an unknown run; Invalid for an empty, too long or garbled text."""
    stored = checked_instruction(instruction)
    with transaction(session):
        run = get_row(session, Run, run_id)
        changed = run.instruction != stored
        run.instruction = stored
        if changed:
            session.flush()
            record_instruction(session, run)
        detach(session, run)
    return run


@dataclass(frozen=True)
class Shown:
    """An instruction as labellers saw it from `since` on."""

    text: str
    sha256: str
    since: datetime


class InstructionHistory:
    """The instructions runs showed over time, to look up by run and moment."""

    def __init__(self, rows: Iterable[RunInstruction]):
        self._by_run: dict[int, list[Shown]] = {}
        for row in sorted(rows, key=lambda r: (r.set_at, r.id)):
            self._by_run.setdefault(row.run_id, []).append(Shown(row.text, row.sha256, row.set_at))

    def at(self, run_id: int, moment: datetime) -> Shown | None:
        """The instruction in force at `moment`; None before the run's first one."""
        shown = self._by_run.get(run_id, [])
        index = bisect.bisect_right([s.since for s in shown], moment)
        return shown[index - 1] if index else None


def instructions_at(session: Session, *, run_ids: Iterable[int]) -> InstructionHistory:
    """The instruction histories of these runs, read in a transaction of its own."""
    ids = sorted(set(run_ids))
    with transaction(session):
        rows = list(session.scalars(select(RunInstruction).where(RunInstruction.run_id.in_(ids))))
    return InstructionHistory(rows)

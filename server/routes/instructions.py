"""A run's instruction to labellers: the operator edits it; the label page reads it, with how
the run's clips relate to the task's own time, for the run of the pair on screen."""

from __future__ import annotations

from fastapi import APIRouter

from crowdstudy.invites import invite_run
from labelqueue import OtherRun, set_instruction
from runvocab.clip_format import (
    CLIP_FPS,
    CLIP_SIZES,
    DEFAULT_CLIP_SIZE,
    real_time_ratio,
    step_seconds,
)
from runvocab.instructions import instruction_sha256, run_instruction
from server import services
from server.deps import LabellerDep, OperatorDep, SessionDep
from server.label_schemas import RunBrief
from server.schemas import InstructionUpdate, RunId, RunOut, errors

router = APIRouter(prefix="/api", responses=errors(401, 403))


@router.put(
    "/runs/{run_id}/instruction",
    tags=["runs"],
    response_model=RunOut,
    responses=errors(400, 404, 413, 422),
)
def put_instruction(
    run_id: RunId, body: InstructionUpdate, session: SessionDep, _: OperatorDep
) -> RunOut:
    """The run's instruction from now on (null: the task's own). Labels already given keep the
    instruction they were given under, in the export."""
    return RunOut.model_validate(
        set_instruction(session, run_id=run_id, instruction=body.instruction)
    )


@router.get(
    "/label/runs/{run_id}", tags=["label"], response_model=RunBrief, responses=errors(404, 422)
)
def run_brief(run_id: RunId, session: SessionDep, caller: LabellerDep) -> RunBrief:
    """What the label page shows above a pair of this run: its instruction, and how fast its
    clips play against the task's own time. A participant of a one-run invite reads that run's
    only: another's is a 403 naming theirs, as `GET /api/label/next` answers."""
    assert caller.labeller_id is not None
    own = invite_run(session, labeller_id=caller.labeller_id)
    if own is not None and own != run_id:
        raise OtherRun.asking(own, run_id)
    run = services.get_run(session, run_id=run_id)
    text = run_instruction(run.task, run.instruction)
    width, height = CLIP_SIZES[run.clip_size or DEFAULT_CLIP_SIZE]
    return RunBrief(
        run_id=run.id,
        task=run.task,
        instruction=text,
        instruction_sha256=instruction_sha256(text),
        clip_width=width,
        clip_height=height,
        fps=CLIP_FPS,
        step_seconds=step_seconds(run.task),
        real_time_ratio=real_time_ratio(run.task),
    )

"""Operator endpoints for runs: create, list, status, metrics, pause/resume/stop, teacher."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Response

from labelqueue import RunStatus, read_metrics, set_run_status, set_teacher
from server import curves, services
from server.deps import OperatorDep, SessionDep
from server.run_check import check_run
from server.schemas import (
    AfterStep,
    MetricOut,
    RunCreate,
    RunId,
    RunOut,
    StreamName,
    TeacherUpdate,
    errors,
)

MOVE_ERRORS = errors(404, 409, 422)

router = APIRouter(prefix="/api/runs", tags=["runs"], responses=errors(401, 403))


@router.post("", status_code=201, response_model=RunOut, responses=errors(400, 413, 422))
def create_run(spec: RunCreate, session: SessionDep, _: OperatorDep) -> RunOut:
    check_run(task=spec.task, algo=spec.algo, preset=spec.preset, seed=spec.seed,
              budget=spec.budget, teacher_params=spec.teacher_params, config=spec.config)
    return RunOut.model_validate(services.new_run(session, spec=spec))


@router.get("", response_model=list[RunOut])
def list_runs(session: SessionDep, _: OperatorDep) -> list[RunOut]:
    return [RunOut.model_validate(run) for run in services.list_runs(session)]


@router.get("/{run_id}", response_model=RunOut, responses=errors(404, 422))
def get_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    return RunOut.model_validate(services.get_run(session, run_id=run_id))


@router.get("/{run_id}/metrics", response_model=list[MetricOut], responses=errors(404, 422))
def get_metrics(
    run_id: RunId,
    session: SessionDep,
    _: OperatorDep,
    stream: StreamName = "episodes",
    after_step: AfterStep = None,
) -> list[MetricOut]:
    services.get_run(session, run_id=run_id)
    rows = read_metrics(session, run_id=run_id, stream=stream, after_step=after_step)
    return [MetricOut.model_validate(row) for row in rows]


@router.get("/{run_id}/curves.png", response_class=Response,
            responses=errors(404, 422, also={200: {"content": {"image/png": {}}}}))
def get_curves_png(
    run_id: RunId,
    session: SessionDep,
    _: OperatorDep,
    metric: Literal["return", "success_rate"] = "return",
) -> Response:
    """The run's evaluation curve beside its peers' (same task, preset and teacher eps), one
    curve per algorithm with its spread across runs: the experiment report's figure."""
    run = services.get_run(session, run_id=run_id)
    png = curves.peer_curves_png(session, run, metric)
    return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})


@router.post("/{run_id}/pause", response_model=RunOut, responses=MOVE_ERRORS)
def pause_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    return RunOut.model_validate(set_run_status(session, run_id=run_id, status=RunStatus.PAUSED))


@router.post("/{run_id}/resume", response_model=RunOut, responses=MOVE_ERRORS)
def resume_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    return RunOut.model_validate(set_run_status(session, run_id=run_id, status=RunStatus.RUNNING))


@router.post("/{run_id}/stop", response_model=RunOut, responses=MOVE_ERRORS)
def stop_run(run_id: RunId, session: SessionDep, _: OperatorDep, force: bool = False) -> RunOut:
    """Running/paused: stopping; queued: stopped; `force=true` also ends a stopping run."""
    return RunOut.model_validate(services.stop_run(session, run_id=run_id, force=force))


@router.post("/{run_id}/requeue", response_model=RunOut, responses=MOVE_ERRORS)
def requeue_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    """A stopped or failed run back in the queue; its next worker resumes its checkpoint."""
    return RunOut.model_validate(set_run_status(session, run_id=run_id, status=RunStatus.QUEUED))


@router.put(
    "/{run_id}/teacher", response_model=RunOut, responses=errors(400, 404, 413, 422)
)
def put_teacher(run_id: RunId, body: TeacherUpdate, session: SessionDep, _: OperatorDep) -> RunOut:
    """The run's teacher from now on, with its parameters checked as a worker will use them."""
    run = services.get_run(session, run_id=run_id)
    check_run(task=run.task, algo=run.algo, preset=run.preset, seed=run.seed, budget=run.budget,
              teacher_params=body.params, config=run.config, params_at="params")
    run = set_teacher(session, run_id=run_id, teacher=body.teacher, params=body.params)
    return RunOut.model_validate(run)

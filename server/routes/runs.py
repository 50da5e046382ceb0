"""Operator endpoints for runs: create, list, status, what each waits for, metrics,
pause/resume/stop, teacher; a new run's defaults; the workers."""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, HTTPException, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from sqlalchemy import select

from externalruns.runs import is_external
from labelqueue import (
    MetricStream,
    Run,
    RunStatus,
    read_metrics,
    reading,
    set_run_status,
    set_teacher,
)
from labelqueue import stop_run as stop_in_queue
from labelqueue.run_config import as_json, fields, overridden, run_config
from runviews.activity import RECENT_WORKER_S, list_workers, runs_activity
from runvocab.config import typed_overrides
from runvocab.names import ConfigError
from server import curves, services
from server.deps import OperatorDep, SessionDep, SettingsDep
from server.run_check import refusal, run_defaults
from server.schemas import (
    CONFIG_MAX_BYTES,
    INT32_MAX,
    ActivityOut,
    AfterStep,
    AlgoName,
    LabellingRunCreate,
    MetricOut,
    PresetName,
    RunConfigOut,
    RunCreate,
    RunDefaults,
    RunId,
    RunOut,
    TaskName,
    TeacherUpdate,
    WorkerOut,
    config_schema,
    errors,
)

MOVE_ERRORS = errors(404, 409, 422)

router = APIRouter(prefix="/api/runs", tags=["runs"], responses=errors(401, 403))


workers_router = APIRouter(prefix="/api/workers", tags=["runs"], responses=errors(401, 403))


@router.post("", status_code=201, response_model=RunOut, responses=errors(400, 413, 422))
def create_run(spec: RunCreate, session: SessionDep, _: OperatorDep) -> RunOut:
    """A queued run; without `budget`, its preset's (or its config's `feedback.budget`)."""
    try:
        if spec.budget is None:  # the config's, read as any config value is ("500" is 500)
            given = typed_overrides({k: v for k, v in spec.config.items()
                                     if k == "feedback.budget"}).get("feedback.budget")
            budget = given if given is not None else run_defaults(
                task=spec.task, algo=spec.algo, preset=spec.preset, config={},
                measured_pace=None)["budget"]
            spec = spec.model_copy(update={"budget": budget})
        run = services.new_run(session, spec=spec)
    except ConfigError as err:
        raise refusal(err, teacher_params=spec.teacher_params, config=spec.config) from None
    return RunOut.model_validate(run)


LABELLING_FIELDS = {"dataset": "dataset", "feedback.budget": "budget",
                    "feedback.per_round": "per_round", "feedback.selection": "selection",
                    "feedback.segment_length": "segment_length", "name": "name"}
"""the paths a labelling run's refusal names, and the body fields that give them"""


@router.get("/labelling", response_model=list[RunOut])
def list_labelling_runs(session: SessionDep, _: OperatorDep) -> list[RunOut]:
    """The labelling-only runs (those over a dataset), oldest first."""
    with reading(session):
        runs = session.scalars(select(Run).where(Run.dataset.is_not(None)).order_by(Run.id))
        return [RunOut.model_validate(run) for run in runs]


@router.post("/labelling", status_code=201, response_model=RunOut,
             responses=errors(400, 413, 422))
def create_labelling_run(spec: LabellingRunCreate, session: SessionDep, _: OperatorDep,
                         settings: SettingsDep) -> RunOut:
    """A queued labelling-only run over a dataset export in the server's datasets folder
    (`<data dir>/datasets`): no training; each round's pairs come from the dataset's episodes
    (uniformly, then by `selection`), their clips rendered from the stored physics states, until
    `budget` answers. A dataset that is missing, of a task this server does not know, without
    physics states or whose spaces disagree with its `sepoa.json`, and rounds that do not fit
    its episodes, are a 422 naming the problem; nothing is stored."""
    from rundata.labelling import create_labelling_run as create

    root = settings.data_dir / "datasets"
    try:
        found = ".." not in spec.dataset.split("/") and (root / spec.dataset).is_dir()
    except OSError:  # a name the system refuses (a segment over 255 bytes)
        found = False
    if not found:
        raise RequestValidationError([{
            "type": "value_error", "loc": ("body", "dataset"),
            "msg": f"no dataset {spec.dataset!r} in the server's datasets folder {root} "
                   f"(sepoa export --dataset {root} --run N writes one there)"}])
    try:
        run = create(session, dataset=str(root / spec.dataset), budget=spec.budget,
                     per_round=spec.per_round, selection=spec.selection,
                     segment_length=spec.segment_length, name=spec.name, preset=spec.preset,
                     seed=spec.seed, teacher=spec.teacher, teacher_params=spec.teacher_params,
                     config=spec.config, instruction=spec.instruction,
                     clip_size=spec.clip_size)
    except ConfigError as err:
        where: tuple[str, ...] = (
            ("body", LABELLING_FIELDS[err.field]) if err.field in LABELLING_FIELDS
            else ("body", "config", err.field) if err.field in spec.config
            else ("body", "teacher_params", err.field.removeprefix("teacher."))
            if err.field.removeprefix("teacher.") in spec.teacher_params else ("body",))
        raise RequestValidationError([{"type": "value_error", "loc": where,
                                       "msg": str(err)}]) from None
    return RunOut.model_validate(run)


CONFIG_QUERY = {"parameters": [{
    "name": "config", "in": "query", "required": False,
    "description": "the run's config overrides, as a JSON object (at most 16 KiB)",
    "content": {"application/json": {"schema": {"type": "object"} | config_schema()}},
}]}
"""`config` as the OpenAPI states it: a JSON object of config fields, as `POST /api/runs`'s"""


@router.get("/defaults", response_model=RunDefaults, responses=errors(422),
            openapi_extra=CONFIG_QUERY)
def get_defaults(
    request: Request,
    session: SessionDep,
    _: OperatorDep,
    task: Annotated[TaskName, Query()],
    algo: Annotated[AlgoName, Query()] = "pebble",
    preset: Annotated[PresetName, Query()] = "small",
) -> RunDefaults:
    """What a new run of this task, algorithm and preset gets unless told otherwise (budget,
    round size, clip length), when its first pairs come, and for S-EPOA how long its skill
    pretraining takes: at the pace this server's workers last reported, else the small
    preset's on 2 CPU cores."""
    config = request.query_params.get("config", "{}")
    try:
        overrides = json.loads(config) if len(config) <= CONFIG_MAX_BYTES else None
    except (ValueError, RecursionError):  # RecursionError: nested deeper than json can follow
        overrides = None
    if not isinstance(overrides, dict):
        raise RequestValidationError([{"type": "value_error", "loc": ("query", "config"),
                                       "msg": "config must be a JSON object of at most "
                                              f"{CONFIG_MAX_BYTES} characters"}])
    return RunDefaults(**run_defaults(task=task, algo=algo, preset=preset, config=overrides,
                                      measured_pace=_pretraining_pace(session)))


def _pretraining_pace(session: Any) -> float | None:
    """The skill pretraining pace (steps/s) the latest worker that pretrained reported."""
    with reading(session):
        progresses = session.scalars(select(Run.progress).order_by(Run.id.desc()).limit(200))
        for progress in progresses:
            pace = (progress or {}).get("pretraining_fps")
            if isinstance(pace, int | float) and pace > 0:
                return float(pace)
    return None


MAX_RUNS_PAGE = 1000
"""the most runs one `GET /api/runs?limit=` lists"""


@router.get("", response_model=list[RunOut], responses=errors(422))
def list_runs(
    session: SessionDep,
    _: OperatorDep,
    limit: Annotated[int | None, Query(ge=1, le=MAX_RUNS_PAGE, description=(
        "the newest this many only (left out: every run)"))] = None,
    before: Annotated[int | None, Query(ge=1, le=INT32_MAX,
                                        description="runs older than this id only")] = None,
) -> list[RunOut]:
    """Every run, oldest first. A page: `limit=N` lists the N newest (older than run `before`
    when given), still oldest first; the next older page is `before=<its first run's id>`. A
    page of `limit` runs may have older ones before it; a shorter one has none."""
    runs = services.list_runs(session, before=before, limit=limit)
    return [RunOut.model_validate(run) for run in runs]


@router.get("/{run_id}", response_model=RunOut, responses=errors(404, 422))
def get_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    return RunOut.model_validate(services.get_run(session, run_id=run_id))


@router.get("/{run_id}/config", response_model=RunConfigOut, responses=errors(404, 409, 422))
def get_run_config(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunConfigOut:
    """What the run trains with: every field of its configuration, those the run sets itself
    marked. A run stored before configurations were kept is resolved as its worker would (409
    when that fails: its worker fails it with the same message)."""
    run = services.get_run(session, run_id=run_id)
    try:
        stored = run.resolved_config or as_json(run_config(run))
    except ConfigError as err:
        raise HTTPException(409, f"run {run_id}'s configuration does not resolve: {err}") \
            from None
    return RunConfigOut(values=fields(stored), overridden=overridden(run),
                        stored=run.resolved_config is not None)


@router.get("/{run_id}/activity", response_model=ActivityOut, responses=errors(404, 422))
def get_activity(run_id: RunId, session: SessionDep, _: OperatorDep) -> ActivityOut:
    """What the run is doing or waiting for now: a free worker, pretraining (with an estimate),
    N answers from K active labellers (and how many are paused by check pairs), exploring or
    training until the next round (with an estimate), or a worker gone silent."""
    run = services.get_run(session, run_id=run_id)
    [activity] = runs_activity(session, [run])
    return ActivityOut(**vars(activity))


@router.get("/{run_id}/metrics", response_model=list[MetricOut], responses=errors(404, 422))
def get_metrics(
    run_id: RunId,
    session: SessionDep,
    _: OperatorDep,
    stream: MetricStream = MetricStream.EPISODES,
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
    """Running/paused: stopping; queued, or no worker holds it: stopped; `force=true` also ends
    a stopping run (`labelqueue.stop_run`)."""
    return RunOut.model_validate(stop_in_queue(session, run_id=run_id, force=force))


@router.post("/{run_id}/requeue", response_model=RunOut, responses=MOVE_ERRORS)
def requeue_run(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunOut:
    """A stopped or failed run back in the queue; its next worker resumes its checkpoint."""
    return RunOut.model_validate(set_run_status(session, run_id=run_id, status=RunStatus.QUEUED))


@router.put(
    "/{run_id}/teacher", response_model=RunOut, responses=errors(400, 404, 409, 413, 422)
)
def put_teacher(run_id: RunId, body: TeacherUpdate, session: SessionDep, _: OperatorDep) -> RunOut:
    """The run's teacher from now on, with its parameters checked as a worker will use them;
    they replace the run's `config`'s own (`teacher.eps`). 409 for a run no worker will train
    again (finished, failed, stopped, stopping: it keeps the teacher it trained with) and for
    an external run (its client's people answer it, no teacher a worker runs)."""
    if is_external(services.get_run(session, run_id=run_id)):
        raise HTTPException(409, f"run {run_id} is an external run: no worker trains it, so it "
                                 "has no teacher to set; the people of its invites answer it")
    try:
        run = set_teacher(session, run_id=run_id, teacher=body.teacher, params=body.params)
    except ConfigError as err:  # located in `params`, the one place the request gives it
        raise refusal(err, teacher_params=body.params, config={}, params_at="params") from None
    return RunOut.model_validate(run)


MAX_WORKERS = 1000
"""the most workers one `GET /api/workers` lists"""


@workers_router.get("", response_model=list[WorkerOut], responses=errors(422))
def get_workers(
    session: SessionDep,
    _: OperatorDep,
    every: Annotated[bool, Query(alias="all", description=(
        "every worker that ever reported, not only those heard from in the last day"))] = False,
    limit: Annotated[int, Query(ge=1, le=MAX_WORKERS)] = 100,
) -> list[WorkerOut]:
    """The trainer workers heard from in the last day (`all=true`: every one that ever
    reported; each worker process is a row of its own, so each restart adds one), the most
    recently seen first, at most `limit`: its host, its run, when it last reported, and
    whether it trains, idles, went silent (no word for a minute) or is dead (five minutes:
    another worker may take its run)."""
    workers = list_workers(session, seen_within_s=None if every else RECENT_WORKER_S, limit=limit)
    return [WorkerOut(**vars(worker)) for worker in workers]

"""External runs over REST (`externalruns`): an operator creates a run no worker trains
and issues its token; the client holding the token uploads clips (MP4 or WebM as they are, or
frame arrays the server encodes), pushes pairs of them and long-polls the answers.

A run token reaches only these routes of its own run: any other route answers it 401, another
run's routes 403. An operator's token reaches every run's.
"""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import logging
import os
import re
import time
import uuid
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi import Path as PathParam
from sqlalchemy import select
from starlette.concurrency import run_in_threadpool

from externalruns.feed import STATES_LIMIT, Cursor, answers_after, pair_states
from externalruns.pairs import PairSpec, clip_key, push_pairs, withdraw_pair
from externalruns.runs import (
    create_external_run,
    is_external,
    issue_run_token,
    revoke_run_token,
    run_of_token,
    run_tokens,
)
from labelqueue import Invalid, Run, RunStatus, read_run, reading
from labelqueue.runs import EXTERNAL
from rundata.clip_codec import encode_mp4, probe_clip
from runvocab.answers import Answer
from runvocab.clip_format import CLIP_FPS, ClipInfo
from server.deps import (
    HEADERS,
    OperatorDep,
    SessionDep,
    SettingsDep,
    bearer_token,
    known_caller,
)
from server.deps import checked_caller as labeller_caller
from server.external_schemas import (
    AnswersOut,
    ClipOut,
    ExternalRunCreate,
    PairKey,
    PairsIn,
    PairState,
    PairStatesOut,
    PushOut,
    RunTokenInfo,
    RunTokenOut,
)
from server.schemas import INT32_MAX, QueryId, RunId, RunOut, errors
from server.settings import Settings
from server.upload_sweep import delete_withdrawn, upload_folder, upload_lock

log = logging.getLogger(__name__)
router = APIRouter(prefix="/api/runs", tags=["external runs"], responses=errors(401, 403))

UPLOADS = re.compile(r"^/api/runs/[0-9]+/clips$")
"""the paths that take a clip's bytes, up to the settings' `clip_upload_bytes`"""
NPY = "application/x-npy"
VIDEO_TYPES = {"video/mp4": "mp4", "video/webm": "webm"}
TokenId = Annotated[int, PathParam(ge=1, le=INT32_MAX, description="the token's id (`run.<id>.`)")]
POLL_S = 0.5
"""how often a waiting answers request looks again"""
SIDES = (16, 1024)
"""the narrowest and the widest a clip's width and height may be, in pixels"""


@router.post("/external", status_code=201, response_model=RunOut,
             responses=errors(400, 413, 422))
def create_run(spec: ExternalRunCreate, session: SessionDep, _: OperatorDep) -> RunOut:
    """A running run that no worker trains: its client, holding a token from
    `POST /api/runs/{id}/tokens`, pushes pairs of clips and reads the answers people give."""
    run = create_external_run(
        session, name=spec.name or f"external: {spec.task}", task=spec.task, budget=spec.budget,
        labels_per_query=spec.labels_per_query, gold_rate=spec.gold_rate,
        gold_min_accuracy=spec.gold_min_accuracy, gold_min_answers=spec.gold_min_answers,
        practice_pairs=spec.practice_pairs, instruction=spec.instruction)
    return RunOut.model_validate(run)


@router.get("/external", response_model=list[RunOut])
def list_runs(session: SessionDep, _: OperatorDep) -> list[RunOut]:
    """The external runs, oldest first."""
    with reading(session):
        runs = session.scalars(select(Run).where(Run.algo == EXTERNAL).order_by(Run.id))
        return [RunOut.model_validate(run) for run in runs]


@router.post("/{run_id}/tokens", status_code=201, response_model=RunTokenOut,
             responses=errors(404, 409, 422))
def create_token(run_id: RunId, session: SessionDep, _: OperatorDep) -> RunTokenOut:
    """A new token scoped to the external run, shown once: it uploads clips, pushes pairs and
    reads answers of this run, and nothing else (409 for a run a worker trains)."""
    return RunTokenOut(run_id=run_id, token=issue_run_token(session, run_id=run_id))


@router.get("/{run_id}/tokens", response_model=list[RunTokenInfo], responses=errors(404, 422))
def list_tokens(run_id: RunId, session: SessionDep, _: OperatorDep) -> list[RunTokenInfo]:
    """The run's tokens, oldest first, revoked ones too, without their secrets."""
    return [RunTokenInfo.model_validate(row) for row in run_tokens(session, run_id=run_id)]


@router.post("/{run_id}/tokens/{token_id}/revoke", response_model=RunTokenInfo,
             responses=errors(404, 422))
def revoke_token(run_id: RunId, token_id: TokenId, session: SessionDep,
                 _: OperatorDep) -> RunTokenInfo:
    """Revoke one of the run's tokens: its next request, and a wait for answers it has open,
    get a 401. Revoking it again changes nothing; 404 for a token that is not this run's."""
    return RunTokenInfo.model_validate(revoke_run_token(session, run_id=run_id,
                                                        token_id=token_id))


async def run_client(run_id: RunId, request: Request, session: SessionDep,
                     settings: SettingsDep) -> Run:
    """The external run a request may reach: its own run token's, or any with an operator's
    token (401 for no valid token, 403 for another run's token or a labeller's, 404 for no run,
    409 for a run a worker trains)."""
    token = bearer_token(request)
    caller = known_caller(settings=settings, token=token)  # 401 without a token
    if caller is None:
        assert token is not None
        scoped = await run_in_threadpool(run_of_token, session, token=token)
        if scoped is None:
            caller = await run_in_threadpool(labeller_caller, session=session, token=token)
            if caller.role.value != "operator":
                raise HTTPException(403, f"labeller {caller.name!r} is neither an operator nor "
                                         "this run's client")
        elif scoped != run_id:
            raise HTTPException(403, f"this token is scoped to run {scoped}, not run {run_id}")
        else:
            request.state.run_token = token  # a wait for answers reads it again
    run = await run_in_threadpool(read_run, session, run_id=run_id)
    if not is_external(run):
        raise HTTPException(409, f"run {run_id} is trained by a worker, not an external client")
    return run


ClientRun = Annotated[Run, Depends(run_client)]


def _folder(settings: Settings, run_id: int) -> Path:
    folder = upload_folder(settings, run_id)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def stored_clip(settings: Settings, run_id: int, clip_id: str) -> ClipInfo | None:
    """What an uploaded clip holds, from the note written beside it; None when not uploaded."""
    note = upload_folder(settings, run_id) / f"{clip_id}.json"
    try:
        return ClipInfo(**json.loads(note.read_text()))
    except (OSError, ValueError, TypeError):
        return None


def _frames(body: bytes, settings: Settings, fps: float) -> np.ndarray:
    """A frame array sent as a NumPy .npy file: uint8, (frames, height, width, 3), within the
    limits at `fps` before it is encoded (a rate too slow for ffmpeg makes a clip too long)."""
    try:
        frames: np.ndarray = np.load(io.BytesIO(body), allow_pickle=False)
    except (ValueError, OSError, EOFError):
        raise Invalid("the body is not a NumPy .npy array (numpy.save writes one)") from None
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[3] != 3:
        raise Invalid(f"frames must be uint8 of shape (frames, height, width, 3); got "
                         f"{frames.dtype} {tuple(frames.shape)}")
    count, height, width = frames.shape[:3]
    if not 1 <= count <= settings.clip_max_frames:
        raise Invalid(f"{count} frames; a clip holds 1 to {settings.clip_max_frames}")
    if height % 2 or width % 2 or not (_fits(height) and _fits(width)):
        raise Invalid(f"frames are {width}x{height}; width and height must be even, in "
                      f"[{SIDES[0]}, {SIDES[1]}] (yuv420p halves the colour planes)")
    if count / fps > settings.clip_max_seconds:
        raise Invalid(f"{count} frames at fps={fps:g} last {count / fps:.4g} s; at most "
                      f"{settings.clip_max_seconds:.0f} s")
    return frames


def _fits(side: int) -> bool:
    return SIDES[0] <= side <= SIDES[1]


def clip_id_of(body: bytes, kind: str, fps: float) -> str:
    """An uploaded clip's id: the hash of its bytes, and of a frame array's frame rate (the
    same frames at another rate are another clip)."""
    rate = f"fps={fps!r};".encode() if kind == NPY else b""
    return hashlib.sha256(rate + body).hexdigest()[:32]


def store_clip(settings: Settings, run_id: int, body: bytes, kind: str, fps: float) -> ClipOut:
    """Check an uploaded clip with the decoder (or encode a frame array) and keep it under the
    clips folder; the same bytes (at the same frame rate) uploaded again are the same clip.
    Invalid naming what is wrong; nothing is kept then."""
    if not body:
        raise Invalid("the body is empty: send the clip's bytes")
    clip_id = clip_id_of(body, kind, fps)
    folder = _folder(settings, run_id)
    note = folder / f"{clip_id}.json"
    info = stored_clip(settings, run_id, clip_id)
    if info is not None:
        with upload_lock(folder):
            try:
                os.utime(note)  # uploaded again: its age as an unused upload starts again
            except FileNotFoundError:
                info = None  # the sweep has just taken it: store it again
    if info is None:
        tmp = folder / f".{clip_id}.{uuid.uuid4().hex[:8]}.tmp.{'mp4' if kind == NPY else kind}"
        note_tmp = note.with_name(f".{note.name}.{uuid.uuid4().hex[:8]}.tmp")
        try:
            if kind == NPY:
                frames = _frames(body, settings, fps)
                encode_mp4(frames, tmp, fps=fps, width=frames.shape[2], height=frames.shape[1])
            else:
                tmp.write_bytes(body)
            info = probe_clip(tmp)
            if kind != NPY and info.container != kind:
                raise Invalid(f"the body is {info.container.upper()}, sent as video/{kind}")
            if not (_fits(info.width) and _fits(info.height)):
                raise Invalid(f"the clip is {info.width}x{info.height}; its width and height "
                              f"must be in [{SIDES[0]}, {SIDES[1]}]")
            if info.frames > settings.clip_max_frames:
                raise Invalid(f"the clip has {info.frames} frames; at most "
                                 f"{settings.clip_max_frames}")
            if info.seconds > settings.clip_max_seconds:
                raise Invalid(f"the clip lasts {info.seconds:.1f} s; at most "
                                 f"{settings.clip_max_seconds:.0f} s")
            note_tmp.write_text(json.dumps(info.as_json()))
            with upload_lock(folder):  # not while the sweep deletes an older copy
                os.replace(tmp, settings.clips_root / clip_key(run_id, clip_id, info.container))
                os.replace(note_tmp, note)  # last: a clip is uploaded once its note exists
        finally:
            tmp.unlink(missing_ok=True)
            note_tmp.unlink(missing_ok=True)
    return ClipOut(clip_id=clip_id, **info.as_json())


BYTES = {"schema": {"type": "string", "format": "binary"}}


@router.post("/{run_id}/clips", status_code=201, response_model=ClipOut,
             responses=errors(404, 409, 413, 415, 422), openapi_extra={"requestBody": {
                 "required": True,
                 "content": {kind: BYTES for kind in ("video/mp4", "video/webm", NPY)}}})
async def upload_clip(
    run: ClientRun, request: Request, response: Response, settings: SettingsDep,
    fps: Annotated[float, Query(gt=0, le=240, description="a frame array's frame rate")] =
        CLIP_FPS,
) -> ClipOut:
    """One clip, as the body: an MP4 (h264) or WebM (VP8, VP9, AV1) file, decoded whole to
    check it against the server's limits (`clip_upload_bytes`, `clip_max_seconds`,
    `clip_max_frames`, sides of 16 to 1024 pixels), or a frame array (`application/x-npy`:
    uint8 (frames, height, width, 3), as `numpy.save` writes it), encoded with the app's own
    clip encoder (h264, yuv420p).
    Its id names it in `POST /api/runs/{id}/pairs`; the same bytes again give the same id
    (200), a frame array's at the same `fps` only. An unreadable file, a codec browsers do not
    play, a clip over a limit: 422, nothing kept. A clip no pair names is deleted
    `unused_upload_hours` after its last upload, or once its run is stopped
    (`server.upload_sweep`)."""
    content_type = request.headers.get("content-type", "").partition(";")[0].strip().lower()
    kind = NPY if content_type == NPY else VIDEO_TYPES.get(content_type)
    if kind is None:
        raise HTTPException(415, f"content type {content_type or 'none'!r}: send video/mp4, "
                                 f"video/webm or {NPY}")
    body = await request.body()
    known = stored_clip(settings, run.id, clip_id_of(body, kind, fps)) is not None
    out = await run_in_threadpool(store_clip, settings, run.id, body, kind, fps)
    if known:
        response.status_code = 200
    return out


@router.post("/{run_id}/pairs", status_code=201, response_model=PushOut,
             responses=errors(400, 404, 409, 413, 422))
def push(run_id: RunId, body: PairsIn, run: ClientRun, response: Response, session: SessionDep,
         settings: SettingsDep) -> PushOut:
    """Pairs of uploaded clips for people to compare, all stored or none: 1 to 500 in a body
    of at most the server's `body_limit_bytes` (64 KiB by default; 413 past it). Each carries an
    idempotency key: pushed again under its key, a pair is not stored twice (its query comes
    back with `created` false, 200 when none is new); other content under a used key is a 409.
    `returns`, `trajectory_returns` and `meta` are hidden from labellers; a `gold` pair's
    known answer measures them. 422 for a clip not uploaded to the run or two clips of
    different shapes or lengths in seconds; 409 past the budget or once the run is stopped."""
    ids = {clip for pair in body.pairs for clip in (pair.first_clip, pair.second_clip)}
    # From reading the notes to the commit: a withdrawal deletes no clip these pairs name.
    with upload_lock(_folder(settings, run.id)):
        clips = {clip: info for clip in ids
                 if (info := stored_clip(settings, run.id, clip)) is not None}
        pushed = push_pairs(session, run_id=run.id, clips=clips, pairs=[
            PairSpec(key=pair.key, first_clip=pair.first_clip, second_clip=pair.second_clip,
                     gold=None if pair.gold is None else Answer(pair.gold),
                     returns=pair.returns, trajectory_returns=pair.trajectory_returns,
                     meta=pair.meta)
            for pair in body.pairs])
    if not any(item.created for item in pushed):
        response.status_code = 200
    return PushOut.model_validate({"pairs": [vars(item) for item in pushed]})


@router.get("/{run_id}/pairs", response_model=PairStatesOut, responses=errors(404, 409, 422))
def states(
    run: ClientRun, session: SessionDep,
    key: Annotated[list[PairKey], Query(
        min_length=1, max_length=STATES_LIMIT, description=(
            f"a pushed pair's idempotency key, given once per key (1 to {STATES_LIMIT})"))],
) -> PairStatesOut:
    """Where the run's pairs under these keys stand now: each with the fields an answers event
    carries for its pair (standing answers, aggregate, tie, complete), and the keys no pair of
    the run has. A client that read past a pair's answers in the feed (before a restart, or
    while waiting for other pairs) learns here that the pair has them."""
    found, unknown = pair_states(session, run_id=run.id, keys=key)
    return PairStatesOut.model_validate({"pairs": found, "unknown": unknown})


@router.post("/{run_id}/pairs/{query_id}/withdraw", response_model=PairState,
             responses=errors(404, 409, 422))
def withdraw(query_id: QueryId, run: ClientRun, session: SessionDep,
             settings: SettingsDep) -> PairState:
    """Withdraw a pushed pair nobody has answered (one pushed by mistake): it is shown to no
    labeller again, one who has it on screen is refused the answer (409), the answers it
    asked of the budget are free again, and its uploaded clips that no other pair shows are
    deleted (a pair naming one again needs it uploaded again). Its key stays used: pushed
    again, it comes back withdrawn. Gives the pair as it stands, `withdrawn`; withdrawing it
    again changes nothing. 409 for a pair with an answer (one of its k is enough) or one of the
    run's practice pairs; 404 for no pair of the run."""
    key = withdraw_pair(session, run_id=run.id, query_id=query_id)
    try:  # after the commit: a refused or failed withdrawal deletes nothing
        delete_withdrawn(session, settings, run_id=run.id, query_id=query_id)
    except OSError:  # withdrawn all the same: the upload sweep takes the clips later
        log.exception("deleting the clips of run %d's withdrawn pair %d failed", run.id,
                      query_id)
    [state], _ = pair_states(session, run_id=run.id, keys=[key])
    return PairState.model_validate(state)


@router.get("/{run_id}/answers", response_model=AnswersOut, responses=errors(404, 409, 422))
async def answers(
    run: ClientRun, request: Request, session: SessionDep,
    after: Annotated[str, Query(max_length=40, description=(
        "the cursor the last read gave, the run's id, a label's and a withdrawal's joined by "
        "dots ('7.57.2'; '0.0': from the start); one this run never gave, another run's, "
        "one naming run 0 or one of two numbers but the start, is refused (422)"))] = "0.0",
    wait: Annotated[float, Query(ge=0, le=60, description="seconds to wait for an answer when "
                                                         "there is none yet")] = 0.0,
) -> AnswersOut:
    """The run's answers and withdrawals after the cursor `after`, oldest first: each with its
    pair's key and hidden metadata, each labeller's standing answer, their aggregate (the
    majority of k; can't-tell on a tie, `tie` set) and whether the pair has its k answers. An
    answer taken back after it was read comes again as a withdrawal. With `wait`, the request
    is held until there is something new or the seconds pass. Keep the `cursor` it gives: read
    from it after a crash, nothing is lost and nothing comes twice. 422 for a cursor this run
    never gave: another run's, or one ahead of its answers."""
    try:
        cursor = Cursor.parse(after)
    except ValueError as err:
        raise HTTPException(422, str(err)) from None
    deadline = time.monotonic() + wait
    token: str | None = getattr(request.state, "run_token", None)
    while True:
        feed = await run_in_threadpool(answers_after, session, run_id=run.id, cursor=cursor)
        if feed.events or time.monotonic() >= deadline or feed.status not in (
                RunStatus.RUNNING.value, RunStatus.PAUSED.value):
            break
        await asyncio.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
        if token is not None and await run_in_threadpool(
                run_of_token, session, token=token) != run.id:
            raise HTTPException(401, "this run token was revoked", HEADERS)
    return AnswersOut(events=feed.events, cursor=str(feed.cursor),  # type: ignore[arg-type]
                      open_pairs=feed.open_pairs, status=feed.status)

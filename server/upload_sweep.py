"""Uploaded clips that no pair uses are deleted (`server.routes.external` keeps the uploads).

A client uploads a clip, then pushes pairs naming it; a clip no pair names takes disk for
nothing. Every `upload_sweep_seconds` the server looks through each external run's uploads
(`clips/external/<run id>/`) and deletes a clip that no pair of its run names when

- it was last uploaded more than `unused_upload_hours` ago (the same bytes uploaded again count
  as a new upload), or
- its run takes no pairs any more (stopped, finished or failed): at once, whatever its age. A
  requeued run's client uploads again (`sepoa.client` uploads a pair's clips before every push;
  the same bytes get the same id).

A clip named by a pair is never deleted. Deleting takes two sweeps, so that a push that read a
clip's note just before a sweep cannot lose it: the first sweep renames the note
(`<id>.json` -> `<id>.json.unused`), after which no push can name the clip (422, "no clip
uploaded"; uploading it again restores it); the next sweep deletes clip and note, unless a pair
names the clip by then (a push that was under way), in which case the note is put back.
An upload and a sweep of the same run take turns (a lock file, `.lock`, in the run's folder),
so a clip uploaded again while the sweep deletes it is whole when its upload returns. Leftovers
of an upload cut short (dot files) go after an hour.

A withdrawn pair names no clip: its clips that no other pair of the run shows are deleted at
once, once the withdrawal has committed (`delete_withdrawn`), under the same lock, which a push
holds from reading its clips' notes until it commits, so no pair is stored naming a clip that
is being deleted (the push is a 422, "no clip uploaded", instead). A clip a withdrawal left
(the server stopped in between) is an unused upload for the sweep.
"""

from __future__ import annotations

import asyncio
import fcntl
import logging
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from externalruns.pairs import ClipUse, clip_use, withdrawn_clips
from server.settings import Settings

log = logging.getLogger(__name__)

UNUSED = ".unused"
"""the suffix a note gets when its clip is to be deleted at the next sweep"""
TMP_MAX_AGE_S = 3600.0
"""how old a leftover of an upload cut short may be"""


@dataclass
class Swept:
    """What one sweep did, in clips."""

    marked: int = 0
    """notes renamed: their clips go at the next sweep"""
    deleted: int = 0
    kept: int = 0
    """marked clips a pair named by the next sweep (or uploaded again): kept"""


def sweep_uploads(session: Session, settings: Settings, now: float | None = None) -> Swept:
    """One sweep over every external run's uploads; `now` as `time.time()` says it."""
    now = time.time() if now is None else now
    root = settings.clips_root / "external"
    swept = Swept()
    if not root.is_dir():
        return swept
    use = clip_use(session)
    limit_s = settings.unused_upload_hours * 3600
    for folder in root.iterdir():
        if not (folder.is_dir() and folder.name.isdigit() and int(folder.name) in use):
            continue  # a folder of no external run this database knows: not ours to judge
        run = use[int(folder.name)]
        with upload_lock(folder):
            _sweep_folder(folder, run, now, limit_s, swept)
    return swept


def upload_folder(settings: Settings, run_id: int) -> Path:
    """The folder of an external run's uploaded clips and their notes (the one
    `externalruns.pairs.clip_key` names)."""
    return settings.clips_root / "external" / str(run_id)


@contextmanager
def upload_lock(folder: Path) -> Iterator[None]:
    """Hold the run folder's lock: uploads to the run and a sweep of it take turns."""
    with open(folder / ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def delete_withdrawn(session: Session, settings: Settings, *, run_id: int,
                     query_id: int) -> int:
    """Delete the clips (files and notes) of the run's withdrawn pair `query_id` that no other
    pair of the run shows; how many clips were there to delete. A clip already gone is fine."""
    folder = upload_folder(settings, run_id)
    if not folder.is_dir():
        return 0
    with upload_lock(folder):
        keys = withdrawn_clips(session, run_id=run_id, query_id=query_id)
        for key in keys:
            clip = settings.clips_root / key
            for note in (clip.with_suffix(".json"), clip.with_suffix(".json" + UNUSED)):
                note.unlink(missing_ok=True)  # first: the clip is no longer uploaded
            clip.unlink(missing_ok=True)
    return len(keys)


def _sweep_folder(folder: Path, run: ClipUse, now: float, limit_s: float,
                  swept: Swept) -> None:
    for path in folder.iterdir():
        name = path.name
        if name.startswith("."):
            if name != ".lock" and _age(path, now) > TMP_MAX_AGE_S:
                path.unlink(missing_ok=True)
            continue
        clip_id = name.partition(".")[0]
        if name.endswith(".json" + UNUSED):
            note = path.with_name(f"{clip_id}.json")
            if note.exists():  # uploaded again since: the fresh note stands
                path.unlink(missing_ok=True)
                swept.kept += 1
            elif clip_id in run.clip_ids:  # a push that was under way named it
                _rename(path, note)
                swept.kept += 1
            else:
                for clip in folder.glob(f"{clip_id}.*"):
                    if clip.suffix in (".mp4", ".webm"):
                        clip.unlink(missing_ok=True)
                path.unlink(missing_ok=True)
                swept.deleted += 1
        elif name.endswith(".json") and clip_id not in run.clip_ids and (
                run.over or _age(path, now) > limit_s):
            if _rename(path, path.with_name(name + UNUSED)):
                swept.marked += 1


def _age(path: Path, now: float) -> float:
    try:
        return now - path.stat().st_mtime
    except FileNotFoundError:
        return 0.0


def _rename(source: Path, target: Path) -> bool:
    """Rename unless another process's sweep or upload got there first."""
    try:
        os.replace(source, target)
    except FileNotFoundError:
        return False
    return True


async def sweep_forever(sessions: sessionmaker[Session], settings: Settings) -> None:
    """Sweep every `upload_sweep_seconds` until cancelled; a sweep that fails is logged and
    the next one runs as usual."""
    while True:
        await asyncio.sleep(settings.upload_sweep_seconds)
        try:
            with sessions() as session:
                swept = await run_in_threadpool(sweep_uploads, session, settings)
            if swept.marked or swept.deleted:
                log.info("unused uploads: %d deleted, %d to go at the next sweep",
                         swept.deleted, swept.marked)
        except Exception:
            log.exception("sweeping the unused uploads failed")

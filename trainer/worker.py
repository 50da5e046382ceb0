"""The trainer worker: claims runs from the queue database, trains them, and hands them back.

    sepoa worker --database-url sqlite:///data/queue.db --data-dir data

A worker trains one run at a time; any number of workers may share one database. For each run
it claims (a queued one, or one whose worker stopped heartbeating), it takes the configuration
stored with the run when it was created (a run stored before that was kept: resolved from the
row's task, algorithm, preset, seed, budget, teacher parameters and config overrides), resumes
from the checkpoint in the run's folder if there is one, and trains with `QueueHooks`.
A run's folder is `<data dir>/runs/run-<id>`; an experiment's run (one with a grid key) goes to
`<results>/<grid key>`, i.e. `<results>/<spec name>/<run folder>`, with its skill snapshots in
`<results>/snapshots`, so every worker given the same (shared) results folder writes the grid
where `sepoa experiment status` and `sepoa report` read it. The worker marks the folder's end:
`done.json` (the run's summary), `stopped.json` (stopped by an operator; its summary) or
`failed.json` (the error). `QueueHooks`:

- heartbeat every few seconds with the run's progress, and obey the operator between steps:
  paused -> wait, stopping/stopped -> end at the episode's end after a checkpoint;
- mirror every metric row into the database for the dashboard;
- push each round's queries, render their clips when people teach the run, and take the
  answers from the queue. A scripted teacher answers through the same queue operations as a
  person (it is the labeller `scripted-teacher`); an operator may switch a live run between
  people and the scripted teacher, and the switch applies to the open round's unanswered
  queries at once.

A worker told to go (SIGTERM: `kill`, `scancel`, a scheduler's preemption, its launcher's stop;
SIGUSR1: the warning Slurm sends before the time limit with `--signal`) ends its run at the end
of the current episode, after a checkpoint, and releases it (`labelqueue.release_run`): the run
is queued again at once, and the next worker resumes it from that checkpoint without waiting
for the heartbeat timeout. Told inside a round's reward training, which can outlast the
warning, it leaves after the current reward epoch with that training saved
(`trainer/round_progress.py`), and the next worker goes on from that epoch. A second such
signal ends the worker at once. A worker with `once` that finds nothing to claim but a run held
by a worker that has gone silent says so, and when the run may be taken over, and waits for it
rather than exit.

A round's labels are read back by query id (`labels_for_queries`), which does not care whether a
label was consumed before: a worker killed after labels arrived resumes from the checkpoint
taken when the round opened, pushes the same queries again (the push is idempotent) and finds
every label given meanwhile. A query is answered when `feedback.labels_per_query` people have
answered it, and their majority is trained on (`runvocab.answers.aggregate`); when the scripted
teacher answered it, its answer is. A round that must end early (the run's end) takes the
answers that arrived. A person's label is used once it is older than `labelqueue.SETTLE_SECONDS`,
when it can no longer be taken back (`labelqueue.undo`); a withdrawn label is never read. When
people teach and `feedback.gold_rate` is above zero, each round also pushes gold pairs
(`trainer.gold_pairs`, `labelqueue.gold`), which measure the labellers and are never trained on.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import sys
import time
import traceback
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    DEAD_WORKER_AFTER_S,
    Conflict,
    Label,
    Labeller,
    LabelSource,
    LeaseError,
    Run,
    RunClosed,
    RunStatus,
    TeacherKind,
    cancel_queries,
    claim_run,
    consume_labels,
    create_labeller,
    find_labeller,
    finish_run,
    heartbeat,
    heartbeat_age,
    labels_for_queries,
    lease_next_query,
    make_engine,
    mask_url,
    migrate,
    push_queries,
    read_run,
    release_run,
    session_factory,
    set_clips,
    settled,
    silent_holders,
    submit_label,
    write_metrics,
)
from labelqueue.models import SCRIPTED_TEACHER
from labelqueue.run_config import run_config as stored_run_config
from rundata.episodes import (
    StoredEpisode,
    episode_path,
    episodes_dir,
    read_end_state,
    write_end_state,
    write_episode,
)
from runvocab.answers import aggregate, click_of_answer
from runvocab.config import RunConfig, apply_overrides
from runvocab.query_fields import QUERY_FIELDS
from trainer.clips import ClipConfig, render_query_clips, sized
from trainer.dataset_labelling import DatasetLabelling
from trainer.envs import Env, make_env
from trainer.feedback import GivenAnswer, PreferenceFeedback, Query
from trainer.gold_pairs import gold_count, gold_pairs, round_layout
from trainer.hooks import RunHooks
from trainer.loop import CHECKPOINT, TrainingRun
from trainer.trajectories import Trajectory, TrajectoryPool

SCRIPTED_LABELLER = SCRIPTED_TEACHER
SCRIPTED_LEASE_RETRIES = 100
"""leases of one query the scripted teacher may lose in a row to other workers before it gives up"""
DONE, FAILED, STOPPED = "done.json", "failed.json", "stopped.json"
"""a run folder's end, as the worker marks it"""


@dataclass(frozen=True)
class WorkerConfig:
    """One worker process."""

    database_url: str
    """the queue database"""
    data_dir: Path
    """runs go to <data_dir>/runs/run-<id>, clips to <data_dir>/clips (or clips_dir)"""
    clips_dir: Path | None = None
    """where clips are written; the server must serve the same folder"""
    worker_id: str = field(default_factory=lambda: f"{socket.gethostname()}-{os.getpid()}")
    """this worker's name in the database"""
    poll_seconds: float = 2.0
    """how often an idle worker looks for a run, and a waiting one for labels"""
    heartbeat_seconds: float = 2.0
    """how often a training worker reports (and reads the operator's commands)"""
    once: bool = False
    """exit when no run is waiting, instead of polling forever"""
    device: str | None = None
    """overrides every run's device (auto | cpu | cuda)"""
    threads: int | None = None
    """overrides every run's torch CPU threads"""
    clip: ClipConfig = field(default_factory=ClipConfig)
    """how clips are rendered; a run's own `clip_size` replaces the width and height"""
    results_dir: Path | None = None
    """experiments' runs go to <results_dir>/<grid key> (default <data_dir>/results)"""

    @property
    def clips_root(self) -> Path:
        return self.clips_dir or self.data_dir / "clips"

    @property
    def results_root(self) -> Path:
        return self.results_dir or self.data_dir / "results"


class LostRun(Exception):
    """The run was given to another worker (requeued, or this one was declared dead)."""


LEAVE_SIGNALS = (signal.SIGTERM, signal.SIGUSR1)
"""the signals that tell a worker to checkpoint, release its run and exit"""


class Departure:
    """Whether, and by which signal, this worker was told to go (`LEAVE_SIGNALS`)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.announced = False

    @property
    def due(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else "none"

    def on_signal(self, signum: int, _frame: Any) -> None:
        # Nothing printed here: the signal may have interrupted a print to the same stream.
        self.signum = signum
        for sig in LEAVE_SIGNALS:  # a second one ends the worker at once
            signal.signal(sig, signal.SIG_DFL)


class Interrupted(Exception):
    """Told to go where no checkpoint can be written (while a skill snapshot is pretrained)."""


def run_config(run: Run, worker: WorkerConfig) -> RunConfig:
    """The config the run was stored with (`labelqueue.run_config`), in this worker's folders;
    ValueError naming a bad field of a run stored without one."""
    cfg = stored_run_config(run)
    if run.grid_key is not None:  # an experiment's run: in the shared results folder
        root, folder = worker.results_root, worker.results_root / run.grid_key
    else:
        root, folder = worker.data_dir, worker.data_dir / "runs" / f"run-{run.id}"
    snapshots = root / "snapshots"
    local: dict[str, object] = {"run_dir": str(folder)}
    # S-EPOA's skill snapshots are shared by the runs of a folder (made on first use, once).
    if "skill.snapshot_dir" not in run.config:
        local["skill.snapshot_dir"] = str(snapshots)
    if worker.device is not None:
        local["device"] = worker.device
    if worker.threads is not None:
        local["threads"] = worker.threads
    return apply_overrides(cfg, local)


def queue_fields(q: Query, position: int,
                 skills: Mapping[int, np.ndarray | None]) -> dict[str, Any]:
    """A trainer query as the queue stores it (`labelqueue.push_queries`): each field that
    `runvocab.query_fields` reads from a trainer attribute, its position in the round, and the
    skill of each side's trajectory (`skills`, by trajectory id)."""
    def skill(trajectory: int) -> list[float] | None:
        vector = skills.get(trajectory)
        return None if vector is None else [float(x) for x in vector]

    made = {declared.name: getattr(q, declared.trainer)
            for declared in QUERY_FIELDS if declared.trainer}
    return made | {"position": position, "first_skill": skill(q.trajectory0),
                   "second_skill": skill(q.trajectory1)}


def complete_queries(labels: Sequence[Label], labels_per_query: int) -> set[int]:
    """The queries whose answers are all in: `labels_per_query` people's, or the scripted
    teacher's (when it teaches, its one answer decides)."""
    counts = Counter(label.query_id for label in labels)
    scripted = {label.query_id for label in labels if label.source is LabelSource.SCRIPTED}
    return scripted | {query for query, n in counts.items() if n >= labels_per_query}


def _answer(given: Sequence[Label], labeller_names: dict[int, str]) -> GivenAnswer:
    """One query's answer from its labels: the scripted teacher's if it answered, else the
    majority of people's (`runvocab.answers.aggregate`). It stands for every one of them: each
    was an answer the queue counted against the budget."""
    scripted = [label for label in given if label.source is LabelSource.SCRIPTED]
    used = scripted[:1] or list(given)
    names = "+".join(labeller_names.get(label.labeller_id, f"labeller-{label.labeller_id}")
                     for label in used)
    return GivenAnswer(aggregate(label.answer for label in used), names, used[0].source.value,
                       max(label.answered_at for label in used).timestamp(), answers=len(given))


class QueueHooks(RunHooks):
    """Connects one training run to the queue database (see the module's docstring)."""

    def __init__(self, sessions: sessionmaker[Session], run: Run, worker: WorkerConfig,
                 cfg: RunConfig, scripted_labeller_id: int, departure: Departure | None = None):
        self.sessions, self.worker, self.cfg = sessions, worker, cfg
        self.departure = departure or Departure()
        self.run_id, self.teacher = run.id, run.teacher
        self.scripted_id = scripted_labeller_id
        self.status = RunStatus.RUNNING
        self.step = 0
        self.progress: dict[str, Any] = {}
        self.next_beat = 0.0
        self.query_ids: dict[str, int] = {}
        self.gold: list[Query] = []
        """the open round's gold pairs (`labelqueue.gold`), pushed among its queries"""
        self.rendered: set[str] = set()
        """the open round's queries whose clips are attached"""
        self.render_env: Env | None = None
        self.clip = sized(worker.clip, run.clip_size)
        """how this run's clips are rendered: the worker's settings at the run's clip size"""
        self.pretrain_start: tuple[float, int] | None = None
        self.last_beat: tuple[float, int] | None = None
        self.next_round_step: Callable[[], int] | None = None
        """the step the training loop opens its next round at (set once it is built)"""
        self.episode_end: Callable[[], np.ndarray] | None = None
        """the training env's physics state, read as an episode ends (set once it is built)"""
        self.episodes = episodes_dir(worker.clips_root, run.id)
        """the run's episode store (`rundata.episodes`)"""
        self.store_episodes = cfg.algo != "sac"
        """whether episodes are kept (a SAC run asks no queries, so none would be read)"""

    # -- operator ------------------------------------------------------------------------------
    def beat(self, step: int, force: bool = False) -> RunStatus:
        """Heartbeat (at most every `heartbeat_seconds` unless forced); the run's status."""
        self.step = step
        now = time.monotonic()
        if not force and now < self.next_beat:
            return self.status
        self.next_beat = now + self.worker.heartbeat_seconds
        self._pace(now, step)
        with self.sessions() as session:
            try:
                schedule = ({} if self.next_round_step is None
                            else {"next_round_step": self.next_round_step()})
                self.status = heartbeat(session, run_id=self.run_id,
                                        worker_id=self.worker.worker_id, step=step,
                                        progress=self.progress | schedule
                                        | {"teacher": self.teacher})
            except Conflict as err:
                raise LostRun(str(err)) from err
            self.teacher = read_run(session, run_id=self.run_id).teacher
        return self.status

    def _pace(self, now: float, step: int) -> None:
        """Steps per second lately (a moving average over the beats), for the estimate of the
        next round: the first episodes' random steps run far faster than training does."""
        last = self.last_beat
        if last is None or step <= last[1]:  # no steps taken (waiting for answers): not counted
            self.last_beat = (now, step)
            return
        if now - last[0] < 0.5:  # beats close together: measure over a longer stretch
            return
        self.last_beat = (now, step)
        rate = (step - last[1]) / (now - last[0])
        old = self.progress.get("steps_per_s")
        self.progress["steps_per_s"] = rate if old is None else 0.7 * old + 0.3 * rate

    def stop_requested(self, step: int) -> bool:
        status = self.beat(step)
        while status is RunStatus.PAUSED and not self.departure.due:
            time.sleep(self.worker.poll_seconds)
            status = self.beat(step, force=True)
        self._announce_departure(f"at step {step}: checkpointing at the end of this episode")
        return self.departure.due or status in (RunStatus.STOPPING, RunStatus.STOPPED)

    def reward_epoch(self, step: int) -> bool:
        # A round's reward training ran 45 min under load: without a heartbeat the run looked
        # dead (300 s) and another worker took it over, throwing the round away. Told to go,
        # the worker leaves after this epoch, its round's training saved: the round could
        # outlast Slurm's warning, and the launcher's grace.
        self.beat(step)
        self._announce_departure(f"inside the round at step {step}: saving its reward training")
        return self.departure.due

    def _announce_departure(self, where: str) -> None:
        """Once, when told to go: where the run is and what the worker does before releasing
        it."""
        if self.departure.due and not self.departure.announced:
            self.departure.announced = True
            print(f"[worker {self.worker.worker_id}] run {self.run_id}: {self.departure.name} "
                  f"{where}, then releasing the run", file=sys.stderr, flush=True)

    def pretraining(self, step: int) -> None:
        # Heartbeats keep the run ours while its skill snapshot is made (minutes to hours);
        # pause and stop wait for the online phase, which can checkpoint. Its pace, for the
        # estimate the run page and the label page show (`labelqueue.activity`).
        if self.departure.due:
            raise Interrupted(f"{self.departure.name} while pretraining the skill snapshot")
        now = time.monotonic()
        if step > 0 and self.pretrain_start is None:
            self.pretrain_start = (now, step)
        self.progress |= {"pretraining_step": step,
                          "pretraining_steps": self.cfg.skill.pretrain_steps}
        if self.pretrain_start is not None and now > self.pretrain_start[0] + 1:
            self.progress["pretraining_fps"] = ((step - self.pretrain_start[1])
                                                / (now - self.pretrain_start[0]))
        self.beat(0)

    def metrics(self, stream: str, row: dict[str, Any]) -> None:
        if stream == "episodes":
            self.progress |= {"episode": row["episode"], "last_return": row["return"],
                              "labels_used": row["labels_used"], "fps": row["fps"]}
        elif stream == "eval":
            self.progress["eval_return"] = row["return"]
        elif stream == "rounds":
            self.progress |= {"round": row["round"], "labels_used": row["labels_used"]}
        if stream == "episodes" and self.episode_end is not None and self.store_episodes:
            # The loop logs an episode before the next reset: the env holds its final state.
            write_end_state(self.episodes, int(row["episode"]) - 1, self.episode_end())
        with self.sessions() as session:
            write_metrics(session, run_id=self.run_id, stream=stream, step=int(row["step"]),
                          values=row)

    # -- queries -------------------------------------------------------------------------------
    def round_opened(self, queries: list[Query], pool: TrajectoryPool) -> None:
        fb = self.cfg.feedback
        # Gold pairs measure people; a round the scripted teacher answers gets none. At least
        # the run's practice pairs, for the practice round of whoever starts now.
        self.gold = [] if self.teacher is not TeacherKind.HUMAN else gold_pairs(
            list(pool.trajectories),
            n=max(gold_count(len(queries), fb.gold_rate), fb.practice_pairs if queries else 0),
            segment_length=fb.segment_length, eps=self.cfg.teacher.eps,
            round_=queries[0].round if queries else 0, seed=self.cfg.seed,
            step=queries[0].step if queries else 0)
        self._store(queries + self.gold, pool)
        skills = {t.id: t.skill for t in pool.trajectories}
        # Gold pairs at random places among the queries: their ids tell nothing.
        pairs, gold = round_layout(queries, self.gold), {q.query_id for q in self.gold}
        specs = [queue_fields(q, i, skills) | ({"gold": True} if q.query_id in gold
                                               else {"needs_labels": fb.labels_per_query})
                 for i, q in enumerate(pairs)]
        with self.sessions() as session:
            ids = push_queries(session, run_id=self.run_id, queries=specs)
        self.query_ids = {q.query_id: db_id for q, db_id in zip(pairs, ids, strict=True)}
        self.rendered = set()
        self.progress["waiting_for"] = len(queries)
        if self.teacher is TeacherKind.HUMAN:
            self._render(pairs, pool)  # in id order, gold pairs among the rest

    def _scratch_env(self) -> Env:
        """An env of the run's task for restoring states (clips, final observations)."""
        if self.render_env is None:
            self.render_env = make_env(self.cfg.task, self.cfg.seed + 200_000,
                                       self.cfg.episode_length or None)
        return self.render_env

    def _store(self, queries: list[Query], pool: TrajectoryPool) -> None:
        """Keep the episodes these queries point into in the run's episode store (those not
        kept yet), before the queries reach the queue."""
        if not self.store_episodes:
            return
        by_id = {t.id: t for t in pool.trajectories}
        wanted = sorted({t for q in queries for t in (q.trajectory0, q.trajectory1)})
        for trajectory in wanted:
            if episode_path(self.episodes, trajectory).is_file():
                continue
            try:
                episode = stored_episode(by_id[trajectory], self._scratch_env(),
                                         read_end_state(self.episodes, trajectory))
            except NotImplementedError as err:  # a task whose states cannot be restored
                print(f"[worker {self.worker.worker_id}] run {self.run_id}: episodes not "
                      f"kept for the dataset export: {err}", file=sys.stderr, flush=True)
                self.store_episodes = False
                return
            write_episode(self.episodes, episode)

    def _render(self, queries: list[Query], pool: TrajectoryPool) -> None:
        """Clips for the queries that have none yet, attached one query at a time so people can
        start on the first while the rest render. A clip already on disk is not rendered again."""
        by_id = {t.id: t for t in pool.trajectories}
        for q in queries:
            if q.query_id in self.rendered:
                continue
            folder = f"run-{self.run_id}"
            stem = f"r{q.round}-{q.query_id.split('-')[-1]}"
            keys = (f"{folder}/{stem}-0.mp4", f"{folder}/{stem}-1.mp4")
            root = self.worker.clips_root
            if not all((root / key).is_file() for key in keys):
                render_query_clips(self._scratch_env(), by_id[q.trajectory0], q.start0,
                                   by_id[q.trajectory1], q.start1, q.segment_length,
                                   root / folder, stem, self.clip)
            with self.sessions() as session:
                set_clips(session, query_id=self.query_ids[q.query_id], first_clip=keys[0],
                          second_clip=keys[1])
            self.rendered.add(q.query_id)
            self.beat(self.step)

    def _answer_as_scripted(self, queries: list[Query]) -> None:
        """The scripted teacher takes every open query of the round it can lease. Every worker on
        a queue answers as the same scripted labeller, and a labeller's lease for one run
        releases the one it held for another: a lease lost to another worker between lease and
        submit is leased again."""
        by_db_id = {self.query_ids[q.query_id]: q for q in queries}
        lost = 0
        with self.sessions() as session:
            while (leased := lease_next_query(session, labeller_id=self.scripted_id,
                                              run_id=self.run_id, gold=False)) is not None:
                query = by_db_id.get(leased.id)
                if query is None:  # an older round's query left open: not this round's to answer
                    cancel_queries(session, run_id=self.run_id, query_ids=[leased.id])
                    continue
                try:
                    submit_label(session, query_id=leased.id, labeller_id=self.scripted_id,
                                 choice=click_of_answer(query.shadow_choice, left_is_first=True),
                                 left_is_first=True, source="scripted")
                except RunClosed:  # stopped meanwhile; the caller's stop check ends the run
                    return
                except LeaseError:
                    lost += 1
                    if lost > SCRIPTED_LEASE_RETRIES:
                        raise
                    continue
                lost = 0

    def answers(self, feedback: PreferenceFeedback, pool: TrajectoryPool,
                final: bool) -> dict[str, GivenAnswer] | None:
        queries = feedback.pending
        ids = [self.query_ids[q.query_id] for q in queries]
        wait = self.cfg.feedback.wait_for_labels
        while True:
            if self.teacher is TeacherKind.SCRIPTED:
                self._answer_as_scripted(queries)
            elif not self.rendered.issuperset(q.query_id for q in queries):
                self._render(queries, pool)  # switched to people mid-round
            with self.sessions() as session:
                labels = labels_for_queries(session, query_ids=ids)
            # A person's answer is used once it can no longer be taken back (labelqueue.undo).
            final_labels = [label for label in labels
                            if label.source is not LabelSource.HUMAN or settled(label.answered_at)]
            done = complete_queries(final_labels, self.cfg.feedback.labels_per_query)
            self.progress["waiting_for"] = len(ids) - len(done)
            if len(done) == len(ids) or final:
                break
            if not wait:
                self.beat(self.step)
                return None
            time.sleep(self.worker.poll_seconds)
            if self.stop_requested(self.step):
                return None

        with self.sessions() as session:
            # The round takes no more answers (a query the scripted teacher answered may still
            # wait for people's), and those it has can no longer be taken back: read after
            # that, they are the answers the queue counted, each paid from the budget. When
            # every query was complete, this adds to what the loop saw only people's answers
            # too fresh to use, to queries the scripted teacher's answer decides.
            cancel_queries(session, run_id=self.run_id, query_ids=ids)
            consume_labels(session, run_id=self.run_id)
            labels = labels_for_queries(session, query_ids=ids)
            names = self._labeller_names(session, {label.labeller_id for label in labels})
        by_db_id = {db_id: qid for qid, db_id in self.query_ids.items()}
        by_query: dict[int, list[Label]] = {}
        for label in labels:
            by_query.setdefault(label.query_id, []).append(label)
        out = {by_db_id[db_id]: _answer(given, names) for db_id, given in by_query.items()}
        self.progress["waiting_for"] = 0
        return out

    @staticmethod
    def _labeller_names(session: Session, ids: set[int]) -> dict[int, str]:
        rows = session.execute(select(Labeller.id, Labeller.name).where(Labeller.id.in_(ids)))
        names = {labeller_id: name for labeller_id, name in rows}
        session.commit()  # end the read: SQLite writers wait on an open transaction
        return names


def stored_episode(traj: Trajectory, env: Env, end_state: np.ndarray | None) -> StoredEpisode:
    """A finished trajectory as the episode store keeps it: its final observation restored
    from `end_state` (the state after its last step), or, without one, recomputed by stepping
    its last state with its last action (`final_resimulated`)."""
    resimulated = end_state is None
    if end_state is None:
        env.reset()  # step() needs an episode under way
        env.restore(traj.states[-1], traj.context)
        final_obs = env.step(traj.actions[-1]).obs
        end_state = env.physics_state()
    else:
        final_obs = env.restore(end_state, traj.context)
    return StoredEpisode(
        trajectory=traj.id,
        observations=np.concatenate([traj.obs, final_obs[None].astype(np.float32)]),
        actions=traj.actions, rewards=traj.true_rewards,
        states=np.concatenate([traj.states, np.asarray(end_state, np.float64)[None]]),
        context=traj.context, success=traj.success, skill=traj.skill,
        final_resimulated=resimulated)


def scripted_labeller_id(sessions: sessionmaker[Session]) -> int:
    """The labeller the scripted teacher answers as, created on first use."""
    with sessions() as session:
        labeller = find_labeller(session, name=SCRIPTED_LABELLER)
        if labeller is None:
            try:
                labeller, _token = create_labeller(session, name=SCRIPTED_LABELLER)
            except Conflict:  # another worker created it just now
                labeller = find_labeller(session, name=SCRIPTED_LABELLER)
        assert labeller is not None
        return labeller.id


def train_claimed_run(sessions: sessionmaker[Session], run: Run, worker: WorkerConfig,
                      scripted_id: int, departure: Departure | None = None) -> RunStatus | None:
    """Train a run this worker has claimed, and end it; its final status (None if lost). Told
    to go (`departure`), the worker releases the run after its checkpoint: queued again."""
    log = f"[worker {worker.worker_id}] run {run.id}"
    departure = departure or Departure()
    if departure.due:  # told to go as it claimed the run: hand it on untouched
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: released "
                        "before training")
    try:
        cfg = run_config(run, worker)
        resume = os.path.exists(os.path.join(cfg.run_dir, CHECKPOINT))
        if not resume and os.path.isdir(cfg.run_dir):
            shutil.rmtree(cfg.run_dir)  # an attempt that died before its first checkpoint
        for marker in (DONE, FAILED, STOPPED):
            Path(cfg.run_dir, marker).unlink(missing_ok=True)
        hooks = QueueHooks(sessions, run, worker, cfg, scripted_id, departure)
        print(f"{log}: {'resuming' if resume else 'starting'} {run.task} {run.algo} "
              f"in {cfg.run_dir}", file=sys.stderr, flush=True)
        if run.dataset is not None:  # a labelling-only run over a dataset: no training
            labelling = DatasetLabelling(cfg, run.dataset, resume=resume, hooks=hooks,
                                         episode_store=hooks.episodes)
            hooks.step = labelling.step
            summary = labelling.train()
        else:
            training = TrainingRun(cfg, resume=resume, progress=False, hooks=hooks)
            # A round opens at the first episode end past its step (fixed-length episodes).
            length = training.env.episode_length
            hooks.next_round_step = lambda: -(-training.next_round_step // length) * length
            hooks.episode_end = training.env.physics_state
            hooks.step = training.step  # a resumed run reports its step before taking one
            summary = training.train()
        hooks.beat(int(summary["step"]), force=True)  # the final step and progress, on record
    except LostRun as err:
        print(f"{log}: lost ({err})", file=sys.stderr, flush=True)
        return None
    except Interrupted as err:
        return _release(sessions, run.id, worker, f"{log}: {err}; released without a new "
                        "checkpoint")
    except Exception as err:  # noqa: BLE001 - any failure ends the run as failed, with why
        traceback.print_exc()
        error = f"{type(err).__name__}: {err}"
        if "cfg" in locals():
            _mark(cfg.run_dir, FAILED, {"reason": error})
        return _end(sessions, run.id, worker, RunStatus.FAILED, error)
    if departure.due and "round_epochs_saved" in summary:
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: the round at step "
                        f"{summary['step']} saved at reward epoch "
                        f"{summary['round_epochs_saved']:.0f} and released; the next worker "
                        "resumes it there")
    if departure.due and summary.get("stopped"):
        return _release(sessions, run.id, worker, f"{log}: {departure.name}: checkpointed at "
                        f"step {summary['step']} and released; the next worker resumes it")
    status = RunStatus.STOPPED if summary.get("stopped") else RunStatus.FINISHED
    print(f"{log}: {status} at step {summary['step']}", file=sys.stderr, flush=True)
    _mark(cfg.run_dir, DONE if status is RunStatus.FINISHED else STOPPED, summary)
    return _end(sessions, run.id, worker, status, None)


def _mark(run_dir: str, name: str, data: dict[str, Any]) -> None:
    """`done.json` / `failed.json` / `stopped.json` in the run's folder, for reports that read
    folders only."""
    path = Path(run_dir, name)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(data | {"at": time.strftime("%Y-%m-%d %H:%M:%S")},
                                  default=str) + "\n")
        os.replace(tmp, path)
    except OSError as err:
        print(f"cannot write {path}: {err}", file=sys.stderr, flush=True)


def _end(sessions: sessionmaker[Session], run_id: int, worker: WorkerConfig, status: RunStatus,
         error: str | None) -> RunStatus | None:
    with sessions() as session:
        try:
            return finish_run(session, run_id=run_id, worker_id=worker.worker_id,
                              status=status, error=error).status
        except Conflict:  # requeued or taken over meanwhile, or force-stopped: not ours to end
            return read_run(session, run_id=run_id).status


def _release(sessions: sessionmaker[Session], run_id: int, worker: WorkerConfig,
             message: str) -> RunStatus | None:
    with sessions() as session:
        try:
            status = release_run(session, run_id=run_id, worker_id=worker.worker_id).status
        except Conflict:  # requeued or taken over meanwhile: not ours to release
            return read_run(session, run_id=run_id).status
    print(f"{message} (now {status})", file=sys.stderr, flush=True)
    return status


def _report_silent(sessions: sessionmaker[Session], worker: WorkerConfig,
                   told: set[tuple[int, str]]) -> bool:
    """Say which runs are held by workers gone silent, and when each may be taken over (once
    per run and holder); whether there are any."""
    with sessions() as session:
        held = silent_holders(session, worker_id=worker.worker_id)
    for run in held:
        if (run.id, str(run.worker_id)) in told or run.heartbeat_at is None:
            continue
        told.add((run.id, str(run.worker_id)))
        age = heartbeat_age(run) or 0.0
        free_at = run.heartbeat_at + timedelta(seconds=DEAD_WORKER_AFTER_S)
        left = max(0.0, DEAD_WORKER_AFTER_S - age)
        print(f"[worker {worker.worker_id}] run {run.id} ({run.grid_key or run.name}) is held "
              f"by worker {run.worker_id}, silent for {age:.0f} s (stopped or dead?); it can "
              f"be taken over at {free_at:%H:%M:%S} UTC, in {left:.0f} s, unless that worker "
              f"comes back{': waiting for it' if worker.once else ''}",
              file=sys.stderr, flush=True)
    return bool(held)


def _held_elsewhere(sessions: sessionmaker[Session], worker: WorkerConfig) -> str:
    """The runs other workers hold, each with its heartbeat's age and when any worker may take
    it over should its worker be dead (one killed a moment ago still looks alive), as the end
    of the exit line."""
    with sessions() as session:
        held = silent_holders(session, worker_id=worker.worker_id, silent_after=0.0)
    parts = []
    for run in held:
        if run.heartbeat_at is None:
            continue
        age = heartbeat_age(run) or 0.0
        free_at = run.heartbeat_at + timedelta(seconds=DEAD_WORKER_AFTER_S)
        parts.append(f"run {run.id} ({run.grid_key or run.name}) is held by worker "
                     f"{run.worker_id}, last heartbeat {age:.0f} s ago (if that worker is "
                     f"dead, a worker started after {free_at:%H:%M:%S} UTC, in "
                     f"{max(0.0, DEAD_WORKER_AFTER_S - age):.0f} s, takes it over)")
    return "; " + "; ".join(parts) if parts else ""


def _leave_on_signals(departure: Departure) -> dict[int, Any]:
    """Install `departure`'s handler for `LEAVE_SIGNALS`; the handlers it replaced (none
    outside the main thread, where signals cannot be handled)."""
    previous: dict[int, Any] = {}
    for sig in LEAVE_SIGNALS:
        try:
            previous[sig] = signal.signal(sig, departure.on_signal)
        except ValueError:  # not the main thread
            break
    return previous


def run_worker(worker: WorkerConfig, departure: Departure | None = None) -> int:
    """Claim and train runs until interrupted (or, with `once`, until none is waiting and none
    is held by a worker gone silent). Told to go (SIGTERM, SIGUSR1), it checkpoints and releases
    its run, and returns."""
    for attempt in range(5):  # the server may be migrating the same database right now
        try:
            migrate(worker.database_url)
            break
        except Exception:  # noqa: BLE001
            if attempt == 4:
                raise
            time.sleep(1.0)
    departure = departure or Departure()
    previous = _leave_on_signals(departure)
    engine = make_engine(worker.database_url)
    sessions = session_factory(engine)
    told: set[tuple[int, str]] = set()
    try:
        scripted_id = scripted_labeller_id(sessions)
        print(f"[worker {worker.worker_id}] waiting for runs in {mask_url(worker.database_url)}",
              file=sys.stderr, flush=True)
        trained = 0
        while not departure.due:
            with sessions() as session:
                run = claim_run(session, worker_id=worker.worker_id)
            if run is None:
                if not _report_silent(sessions, worker, told) and worker.once:
                    print(f"[worker {worker.worker_id}] no run left to claim: exiting"
                          f"{_held_elsewhere(sessions, worker)}", file=sys.stderr, flush=True)
                    return trained
                time.sleep(worker.poll_seconds)
                continue
            train_claimed_run(sessions, run, worker, scripted_id, departure)
            trained += 1
        print(f"[worker {worker.worker_id}] {departure.name}: exiting", file=sys.stderr,
              flush=True)
        return trained
    finally:
        engine.dispose()
        for sig, handler in previous.items():
            signal.signal(sig, handler)

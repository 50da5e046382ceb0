"""The queue hooks: one training run connected to the queue database (`QueueHooks`).

The worker (`trainer.worker`) trains each run it claims with these hooks. They

- heartbeat every few seconds with the run's progress (its next round's step, as the training
  loop's schedule says), and obey the operator between steps: paused -> wait,
  stopping/stopped -> end at the episode's end after a checkpoint;
- mirror every metric row into the database for the dashboard, and keep each ended episode's
  final physics state in the run's episode store (`rundata.episodes`);
- push each round's queries, render their clips when people teach the run, and take the
  answers from the queue. A scripted teacher answers through the same queue operations as a
  person (it is the labeller `scripted-teacher`, answering in segment terms with
  `labelqueue.submit_answer`); an operator may switch a live run between people and the
  scripted teacher, and the switch applies to the open round's unanswered queries at once.

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

import sys
import time
from collections import Counter
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import Any

import numpy as np
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from labelqueue import (
    Conflict,
    Label,
    LabelSource,
    LeaseError,
    Run,
    RunClosed,
    RunStatus,
    TeacherKind,
    cancel_queries,
    consume_labels,
    heartbeat,
    labeller_names,
    labels_for_queries,
    lease_next_query,
    other_claimable,
    push_queries,
    read_run,
    set_clips,
    settled,
    submit_answer,
    write_metrics,
)
from labelqueue.errors import database_reason
from labelqueue.models import SCRIPTED_TEACHER
from rundata.episodes import (
    StoredEpisode,
    episode_path,
    episodes_dir,
    read_end_state,
    write_end_state,
    write_episode,
)
from runvocab.answers import aggregate
from runvocab.config import RunConfig
from runvocab.query_fields import QUERY_FIELDS
from trainer.clips import render_query_clips, sized
from trainer.departure import Departure
from trainer.envs import Env, make_env
from trainer.feedback import GivenAnswer, PreferenceFeedback, Query
from trainer.gold_pairs import gold_count, gold_pairs, round_layout
from trainer.hooks import RunHooks
from trainer.trajectories import Trajectory, TrajectoryPool
from trainer.worker_config import WorkerConfig

SCRIPTED_LABELLER = SCRIPTED_TEACHER
SCRIPTED_LEASE_RETRIES = 100
"""leases of one query the scripted teacher may lose in a row to other workers before it gives up"""


class LostRun(Exception):
    """The run was given to another worker (requeued, or this one was declared dead)."""


class Interrupted(Exception):
    """Told to go where this run has nothing to checkpoint (waiting while another worker
    pretrains the skill snapshot it needs)."""


class SnapshotBusy(Exception):
    """Another worker is pretraining the skill snapshot this run needs, and other runs are
    waiting: the worker sets this one aside and trains one of them meanwhile."""


SET_ASIDE_CHECK_S = 30.0
"""how often a run waiting for another worker's snapshot looks for other runs to train"""


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
    return GivenAnswer(aggregate(label.answer for label in used), names, used[0].source,
                       max(label.answered_at for label in used).timestamp(), answers=len(given))


class QueueHooks(RunHooks):
    """Connects one training run to the queue database (see the module's docstring). Raises
    `LostRun` when the run was given to another worker, `Interrupted` when told to go while
    waiting for another worker's pretraining of the skill snapshot (told to go while this run
    pretrains it, the pretraining leaves with its progress saved: `PretrainingLeft`), and
    `SnapshotBusy` when waiting so while a run other than this one and `set_aside` is
    claimable."""

    def __init__(self, sessions: sessionmaker[Session], run: Run, worker: WorkerConfig,
                 cfg: RunConfig, scripted_labeller_id: int, departure: Departure | None = None,
                 set_aside: Collection[int] = ()):
        self.sessions, self.worker, self.cfg = sessions, worker, cfg
        self.set_aside = frozenset(set_aside)
        """runs this worker set aside already, waiting for snapshots: not a reason to set this
        one aside too"""
        self.next_set_aside_check = 0.0
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
        self.next_round_at: Callable[[], int] | None = None
        """the step the training loop opens its next round at (its schedule, once it starts)"""
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
                schedule = ({} if self.next_round_at is None
                            else {"next_round_step": self.next_round_at()})
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

    def pretraining(self, step: int) -> bool:
        # Heartbeats keep the run ours while its skill snapshot is made (minutes to hours);
        # pause and stop wait for the online phase. Told to go, the pretraining leaves at the
        # end of its episode with its progress saved. Its pace, for the estimate the run page
        # and the label page show (`runviews.activity`).
        self._announce_departure("while pretraining the skill snapshot: leaving at the end of "
                                 "this episode with the pretraining's progress saved")
        now = time.monotonic()
        if step > 0 and self.pretrain_start is None:
            self.pretrain_start = (now, step)
        self.progress |= {"pretraining_step": step,
                          "pretraining_steps": self.cfg.skill.pretrain_steps}
        if self.pretrain_start is not None and now > self.pretrain_start[0] + 1:
            self.progress["pretraining_fps"] = ((step - self.pretrain_start[1])
                                                / (now - self.pretrain_start[0]))
        self.beat(0)
        return self.departure.due

    def waiting_for_snapshot(self) -> None:
        if self.departure.due:
            raise Interrupted(f"{self.departure.name} while waiting for another worker's "
                              "pretraining of the skill snapshot")
        now = time.monotonic()
        # Only a running run is set aside: a paused one waits for its operator, a stopping one
        # ends where it is.
        if self.status is RunStatus.RUNNING and now >= self.next_set_aside_check:
            self.next_set_aside_check = now + SET_ASIDE_CHECK_S
            if self._others_claimable():
                raise SnapshotBusy("another worker is pretraining its skill snapshot")
        self.beat(0)

    def _others_claimable(self) -> bool:
        """Whether a run other than this one and those set aside is claimable. The check only
        saves idle time: a database that does not answer it now is asked again at the next
        check, and the heartbeat, not this, says whether the run is still ours."""
        try:
            with self.sessions() as session:
                return other_claimable(session, worker_id=self.worker.worker_id,
                                       besides=self.set_aside | {self.run_id})
        except DBAPIError as err:
            print(f"[worker {self.worker.worker_id}] run {self.run_id}: could not look for "
                  f"other queued runs ({database_reason(err)}); waiting for the snapshot",
                  file=sys.stderr, flush=True)
            return False

    def started(self, step: int, next_round_at: Callable[[], int] | None) -> None:
        self.step = step  # a resumed run reports its step before taking one
        self.next_round_at = next_round_at

    def episode_ended(self, episode: int, end_state: np.ndarray) -> None:
        if self.store_episodes:
            write_end_state(self.episodes, episode, end_state)

    def metrics(self, stream: str, row: dict[str, Any]) -> None:
        if stream == "episodes":
            self.progress |= {"episode": row["episode"], "last_return": row["return"],
                              "labels_used": row["labels_used"], "fps": row["fps"]}
        elif stream == "eval":
            self.progress["eval_return"] = row["return"]
        elif stream == "rounds":
            self.progress |= {"round": row["round"], "labels_used": row["labels_used"]}
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
                    submit_answer(session, query_id=leased.id, labeller_id=self.scripted_id,
                                  answer=query.shadow_choice)
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
            names = labeller_names(session, ids={label.labeller_id for label in labels})
        by_db_id = {db_id: qid for qid, db_id in self.query_ids.items()}
        by_query: dict[int, list[Label]] = {}
        for label in labels:
            by_query.setdefault(label.query_id, []).append(label)
        out = {by_db_id[db_id]: _answer(given, names) for db_id, given in by_query.items()}
        self.progress["waiting_for"] = 0
        return out


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

"""The scripted teacher as a crowd: simulated labellers that answer a run's queries through the
queue's own operations (create labellers, lease, submit), as people answer through the API.
The tests use it to check that the quality statistics give each labeller's eps and bias back.

Each `SimulatedLabeller` is the paper's noisy teacher (`trainer.teachers.NoisyTeacher`, the
same code a scripted run is labelled by) with its own eps, seen through a screen: the two
segments are put left and right at random, as the server does, and with probability
|2 * left_bias - 1| the labeller clicks its favoured side without looking. So its share of
"left" clicks is `left_bias`, and it guesses (a lapse, in the calibration report's terms) on
that share of the pairs it could tell apart. Queries pushed with `needs_labels` = the crowd's
size are answered by every labeller; with fewer, the labellers share them.

The noisy teacher's band is eps * |R_avg|. A query does not hold R_avg, so the crowd takes the
calibration report's estimate (`labelstats.calibration.estimate_r_avg`) unless given one:
then the report measures the crowd on the scale the crowd answered on.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from labelqueue import (
    Conflict,
    LabelSource,
    Query,
    create_labeller,
    find_labeller,
    lease_next_query,
    submit_label,
)
from labelstats.calibration import RECENT_TRAJECTORIES, estimate_r_avg
from runvocab.answers import click_of_answer
from trainer.teachers import NoisyTeacher, QueryTruth

RAvg = Callable[[Query], float]
"""R_avg for a query: the noisy teacher's band is eps * |R_avg|"""


@dataclass(frozen=True)
class SimulatedLabeller:
    """One simulated person: a noisy teacher with a side it leans to."""

    name: str
    """its labeller name (created when missing)"""
    eps: float
    """the noisy teacher's eps: pairs within eps * |R_avg| of each other are a coin flip"""
    left_bias: float = 0.5
    """its share of "left" clicks; away from 0.5 it clicks that side on a share of all pairs"""
    seed: int = 0
    """seeds the side order, the leaning and the teacher's coin"""

    def __post_init__(self) -> None:
        if not self.eps >= 0:
            raise ValueError(f"{self.name}: eps must be >= 0, got {self.eps}")
        if not 0.0 <= self.left_bias <= 1.0:
            raise ValueError(f"{self.name}: left_bias must be in [0, 1], got {self.left_bias}")


class _Player:
    """A simulated labeller at work: its labeller id, teacher and random streams."""

    def __init__(self, spec: SimulatedLabeller, labeller_id: int):
        self.spec, self.labeller_id = spec, labeller_id
        self.teacher = NoisyTeacher(spec.eps, seed=spec.seed, recent_trajectories=1)
        self.rng = random.Random(spec.seed)
        self.answers = 0

    def choice(self, query: Query, r_avg: float) -> tuple[str, bool]:
        """(the click, whether the first segment was on the left)."""
        left_is_first = self.rng.random() < 0.5
        lean = self.rng.random()
        truth = QueryTruth(
            np.array([query.first_segment_return]), np.array([query.second_segment_return]),
            query.first_trajectory_return, query.second_trajectory_return,
        )
        # The teacher answers every query, leaning or not, so its coin stream stays aligned.
        [answer] = self.teacher.answer([truth], [r_avg])
        bias = self.spec.left_bias
        if lean < abs(2.0 * bias - 1.0):
            return ("left" if bias > 0.5 else "right"), left_is_first
        return click_of_answer(answer.choice, left_is_first).value, left_is_first


def crowd_labeller_id(session: Session, name: str) -> int:
    """The id of the labeller called `name`, created when there is none."""
    found = find_labeller(session, name=name)
    if found is None:
        try:
            found, _token = create_labeller(session, name=name)
        except Conflict:  # created meanwhile by someone else
            found = find_labeller(session, name=name)
    assert found is not None
    return found.id


def estimated_r_avg(session: Session, run_id: int,
                    recent: int = RECENT_TRAJECTORIES) -> RAvg:
    """R_avg per round as the calibration report estimates it, from the run's stored queries."""
    columns = (Query.run_id, Query.round, Query.first_trajectory, Query.second_trajectory,
               Query.first_trajectory_return, Query.second_trajectory_return)
    rows = [row._asdict() for row in session.execute(
        select(*columns).where(Query.run_id == run_id))]
    session.commit()  # end the read: SQLite writers wait on an open transaction
    by_round = estimate_r_avg(rows, recent)
    return lambda query: by_round.get((query.run_id, query.round), 0.0)


def _constant(value: float) -> RAvg:
    return lambda _query: value


def answer_as_crowd(
    session: Session,
    *,
    run_id: int,
    crowd: Sequence[SimulatedLabeller],
    r_avg: RAvg | float | None = None,
    source: LabelSource | str = LabelSource.SCRIPTED,
    limit: int | None = None,
) -> dict[str, int]:
    """Let `crowd` answer the run's open queries, taking turns one query at a time, until none
    of them can lease another (or `limit` answers in all); answers given, per name.

    `r_avg`: a number, a function of the query, or None for the report's estimate (read once,
    at the start: push the round's queries first). The labels are stored with `source`."""
    if len({spec.name for spec in crowd}) != len(crowd):
        raise ValueError("the crowd's names must differ")
    if r_avg is None:
        r_avg = estimated_r_avg(session, run_id)
    band_of = r_avg if callable(r_avg) else _constant(float(r_avg))
    players = [_Player(spec, crowd_labeller_id(session, spec.name)) for spec in crowd]
    given, busy = 0, True
    while busy and (limit is None or given < limit):
        busy = False
        for player in players:
            if limit is not None and given >= limit:
                break
            query = lease_next_query(session, labeller_id=player.labeller_id, run_id=run_id)
            if query is None:
                continue
            click, left_is_first = player.choice(query, band_of(query))
            submit_label(session, query_id=query.id, labeller_id=player.labeller_id,
                         choice=click, left_is_first=left_is_first, source=source)
            player.answers += 1
            given += 1
            busy = True
    return {player.spec.name: player.answers for player in players}

"""Gold pairs: segment pairs whose answer is beyond doubt, to measure labellers with.

A gold pair's true segment returns differ by at least `GOLD_GAP` bands of the run's noisy
teacher, the band being eps times the mean |segment return| of the pool (never less than
`MIN_EPS`, so an exact teacher still gets clearly different pairs). Among random pairs of the
pool that qualify, a round's gold pairs are drawn at random, not the widest gaps, so they do not
all look alike. The draw is seeded by the run and the round: a resumed round draws the same.

`round_layout` puts them at random places among the round's queries, so that no id, position or
order of rendering tells them apart (`labelqueue.gold`).
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from trainer.feedback import Query
from trainer.trajectories import Trajectory

GOLD_GAP = 3.0
"""a gold pair's return gap, in teacher bands"""
MIN_EPS = 0.1
"""the band's eps when the teacher's own is smaller"""
CANDIDATES_PER_PAIR = 50
"""random pairs looked at per gold pair wanted"""


def gold_count(queries: int, rate: float) -> int:
    """Gold pairs a round of `queries` gets at `rate` (at least one when the rate is not 0):
    enough that they are `rate` of the round's pairs, gold ones included. A labeller is served
    a gold pair only in its place among the others (`labelqueue.gold`), so one who sees every
    pair of a round can be given the rate's share only then."""
    if rate <= 0 or queries <= 0:
        return 0
    return max(1, math.ceil(round(rate * queries / (1 - rate), 9)))


def round_layout(queries: list[Query], gold: list[Query]) -> list[Query]:
    """The round's pairs in the order they are pushed, which gives them their positions and
    ids, and rendered: the queries in their own order, the gold pairs at random places among
    them. The places are drawn with a key made of the round's hidden ground truth, which no
    labeller sees (unlike the run's seed, often 0), and so are the same when a resumed worker
    pushes the round again (the push is idempotent per position)."""
    if not gold:
        return list(queries)
    pairs = list(queries) + list(gold)
    truth = repr([(q.query_id, q.trajectory0, q.start0, q.trajectory1, q.start1,
                   q.segment_return0, q.segment_return1, q.trajectory_return0,
                   q.trajectory_return1) for q in pairs])
    key = int.from_bytes(hashlib.sha256(truth.encode()).digest()[:8], "big")
    places = set(np.random.default_rng(key).choice(len(pairs), size=len(gold), replace=False))
    ordinary, checks = iter(queries), iter(gold)
    return [next(checks) if i in places else next(ordinary) for i in range(len(pairs))]


def _segment_return(t: Trajectory, start: int, h: int) -> float:
    return float(t.true_rewards[start:start + h].sum(dtype=np.float64))


def gold_pairs(trajectories: list[Trajectory], *, n: int, segment_length: int, eps: float,
               round_: int, seed: int, step: int) -> list[Query]:
    """Up to `n` gold pairs from `trajectories` (fewer when few pairs qualify), as queries of
    round `round_` whose shadow answer is the true one."""
    h = segment_length
    usable = [t for t in trajectories if t.length >= h]
    if n <= 0 or len(usable) < 2:
        return []
    rng = np.random.default_rng([seed, round_, 0x601D])
    m = n * CANDIDATES_PER_PAIR
    picks = rng.integers(0, len(usable), size=(m, 2))
    pairs = []
    for a, b in picks:
        t0, t1 = usable[a], usable[b]
        s0 = int(rng.integers(0, t0.length - h + 1))
        s1 = int(rng.integers(0, t1.length - h + 1))
        pairs.append((t0, s0, t1, s1, _segment_return(t0, s0, h), _segment_return(t1, s1, h)))
    scale = float(np.mean([abs(r) for *_, r0, r1 in pairs for r in (r0, r1)]))
    band = max(eps, MIN_EPS) * scale
    qualify = [p for p in pairs if abs(p[4] - p[5]) >= GOLD_GAP * band and p[4] != p[5]]
    chosen = rng.permutation(len(qualify))[:n]
    queries = []
    for i, index in enumerate(sorted(chosen)):
        t0, s0, t1, s1, r0, r1 = qualify[index]
        queries.append(Query(
            query_id=f"r{round_}-g{i}", round=round_, step=step,
            trajectory0=t0.id, start0=s0, trajectory1=t1.id, start1=s1, segment_length=h,
            segment_return0=r0, segment_return1=r1,
            trajectory_return0=t0.true_return, trajectory_return1=t1.true_return,
            model_p=float("nan"), score=float("nan"), rule="gold",
            shadow_choice="first" if r0 > r1 else "second", distinguishable=True,
        ))
    return queries

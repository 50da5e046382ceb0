"""Gold pairs are pairs whose answer is beyond doubt: their true segment returns differ by far
more than the teacher's band, and the same run and round always draw the same ones."""

from __future__ import annotations

import numpy as np
import pytest

from trainer.feedback import Query
from trainer.gold_pairs import GOLD_GAP, gold_count, gold_pairs
from trainer.trajectories import Trajectory

H = 5


def trajectory(id: int, rewards: list[float] | np.ndarray) -> Trajectory:
    rewards = np.asarray(rewards, np.float32)
    t = len(rewards)
    return Trajectory(id=id, obs=np.zeros((t, 3), np.float32), actions=np.zeros((t, 2), np.float32),
                      true_rewards=rewards, states=np.zeros((t, 4)), context=0, success=False)


def pool() -> list[Trajectory]:
    """Segment returns 5 (id 0), 5.05 (id 1) and 15 (id 2): only pairs with id 2 are clear."""
    return [trajectory(0, [1.0] * 20), trajectory(1, [1.01] * 20), trajectory(2, [3.0] * 20)]


def key(q: Query) -> tuple[int, int, int, int]:
    return (q.trajectory0, q.start0, q.trajectory1, q.start1)


@pytest.mark.parametrize(
    ("queries", "rate", "expected"),
    # rate of the round's pairs, gold ones included: 3 of 13 at 0.2, 50 of 100 at 0.5
    [(10, 0.0, 0), (0, 0.2, 0), (10, 0.2, 3), (10, 0.25, 4), (3, 0.1, 1), (50, 0.5, 50),
     (8, 0.2, 2)],
)
def test_gold_count(queries: int, rate: float, expected: int) -> None:
    assert gold_count(queries, rate) == expected


def test_gold_pairs_have_a_clear_answer_and_say_it() -> None:
    trajectories = pool()
    pairs = gold_pairs(trajectories, n=4, segment_length=H, eps=0.1, round_=2, seed=7, step=900)
    assert len(pairs) == 4
    assert len({q.query_id for q in pairs}) == 4
    by_id = {t.id: t for t in trajectories}
    for q in pairs:
        # Never the near-twins 0 and 1: one side is always the far better trajectory 2.
        assert 2 in (q.trajectory0, q.trajectory1) and q.trajectory0 != q.trajectory1
        assert q.round == 2 and q.step == 900 and q.segment_length == H and q.rule == "gold"
        for traj, start, ret in ((q.trajectory0, q.start0, q.segment_return0),
                                 (q.trajectory1, q.start1, q.segment_return1)):
            assert 0 <= start <= by_id[traj].length - H
            assert ret == pytest.approx(float(by_id[traj].true_rewards[start:start + H].sum()))
        better = "first" if q.trajectory0 == 2 else "second"
        assert q.shadow_choice == better and q.distinguishable
        assert abs(q.segment_return0 - q.segment_return1) >= GOLD_GAP * 0.1 * 5


def test_the_segment_return_decides_not_the_trajectory_return() -> None:
    # One trajectory: a bad first half and a good second half; the other flat and middling.
    mixed = trajectory(0, [0.0] * 10 + [4.0] * 10)
    flat = trajectory(1, [1.0] * 20)
    pairs = gold_pairs([mixed, flat], n=3, segment_length=H, eps=0.1, round_=0, seed=1, step=0)
    assert pairs
    for q in pairs:
        assert abs(q.segment_return0 - q.segment_return1) > 0
        assert q.shadow_choice == ("first" if q.segment_return0 > q.segment_return1 else "second")


def test_a_noisy_teacher_widens_the_gap_so_no_pair_may_qualify() -> None:
    # eps 2: the band is twice the mean return, three bands are more than any gap here.
    assert gold_pairs(pool(), n=4, segment_length=H, eps=2.0, round_=0, seed=0, step=0) == []


def test_an_exact_teacher_still_gets_the_minimum_band() -> None:
    exact = gold_pairs(pool(), n=3, segment_length=H, eps=0.0, round_=1, seed=3, step=0)
    minimum = gold_pairs(pool(), n=3, segment_length=H, eps=0.1, round_=1, seed=3, step=0)
    assert exact and [key(q) for q in exact] == [key(q) for q in minimum]
    for q in exact:
        assert 2 in (q.trajectory0, q.trajectory1)


def test_the_same_run_and_round_draw_the_same_pairs() -> None:
    def draw(seed: int, round_: int) -> list[tuple[int, int, int, int]]:
        pairs = gold_pairs(pool(), n=3, segment_length=H, eps=0.1, round_=round_, seed=seed,
                           step=0)
        return [key(q) for q in pairs]

    assert draw(5, 1) == draw(5, 1)  # a resumed round
    assert draw(5, 1) != draw(5, 2) or draw(5, 1) != draw(6, 1)


def test_nothing_to_draw_from() -> None:
    short = [trajectory(0, [1.0] * 3), trajectory(1, [9.0] * 3)]  # shorter than a segment
    assert gold_pairs(short, n=2, segment_length=H, eps=0.1, round_=0, seed=0, step=0) == []
    assert gold_pairs(pool()[:1], n=2, segment_length=H, eps=0.1, round_=0, seed=0, step=0) == []
    assert gold_pairs(pool(), n=0, segment_length=H, eps=0.1, round_=0, seed=0, step=0) == []

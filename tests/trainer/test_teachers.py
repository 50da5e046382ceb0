import math

import numpy as np
import pytest

from runvocab.answers import Answer
from runvocab.config import TeacherConfig
from trainer.teachers import (
    BPrefTeacher,
    NoisyTeacher,
    QueryTruth,
    TeacherAnswer,
    choice_target,
    make_teacher,
)


def truth(seg0, seg1, ret0=0.0, ret1=0.0) -> QueryTruth:
    return QueryTruth(np.asarray(seg0, float), np.asarray(seg1, float), ret0, ret1)


def bpref(seed: int = 0, segment_length: int = 2, episode_length: int = 10, **kw) -> BPrefTeacher:
    return BPrefTeacher(TeacherConfig(kind="bpref", **kw), seed, segment_length, episode_length)


def two_sided_ok(count: int, n: int, p: float) -> bool:
    """count within 5 standard deviations of n * p (false failure rate ~ 1e-6)."""
    return abs(count - n * p) <= 5 * math.sqrt(n * p * (1 - p))


RECENT = [100.0] * 10  # R_avg = 100


# ---------------------------------------------------------------------------------------------
# choice_target, make_teacher


def test_choice_target_mapping():
    assert choice_target(Answer.FIRST) == 0.0
    assert choice_target(Answer.SECOND) == 1.0
    assert choice_target(Answer.EQUAL) == 0.5
    assert choice_target(Answer.CANT_TELL) is None
    assert choice_target(Answer.SKIP) is None
    assert choice_target("second") == 1.0  # StrEnum: raw stored strings work too


def test_make_teacher_kinds():
    noisy = make_teacher(TeacherConfig(kind="noisy", eps=0.3), 0, 50, 1000)
    assert isinstance(noisy, NoisyTeacher) and noisy.eps == 0.3
    assert isinstance(make_teacher(TeacherConfig(kind="bpref"), 0, 50, 1000), BPrefTeacher)
    with pytest.raises(ValueError, match=r"'human'.*noisy.*bpref"):
        make_teacher(TeacherConfig(kind="human"), 0, 50, 1000)


# ---------------------------------------------------------------------------------------------
# NoisyTeacher


def test_noisy_outside_band_segments_decide():
    t = NoisyTeacher(eps=0.3, seed=0)
    # Trajectory 0 has the better return, but segment 1 has the larger sum: segments decide.
    out = t.answer(
        [
            truth([1, 1], [2, 2], ret0=200.0, ret1=10.0),
            truth([3, 3], [2, 2], ret0=10.0, ret1=200.0),
        ],
        RECENT,
    )
    assert out == [
        TeacherAnswer(Answer.SECOND, distinguishable=True, correct=True),
        TeacherAnswer(Answer.FIRST, distinguishable=True, correct=True),
    ]


def test_noisy_equal_segment_sums_outside_band():
    t = NoisyTeacher(eps=0.3, seed=0)
    [a] = t.answer([truth([1, 2], [2, 1], ret0=0.0, ret1=100.0)], RECENT)
    assert a == TeacherAnswer(Answer.EQUAL, distinguishable=True, correct=None)


def test_tied_segment_sums_answer_as_teacher_tie_says():
    tied = [truth([0, 0], [0, 0], ret0=0.0, ret1=100.0)] * 400  # outside the band
    first = NoisyTeacher(eps=0.3, seed=0, tie="first").answer(tied, RECENT)
    assert {a.choice for a in first} == {Answer.FIRST}
    coin = [a.choice for a in NoisyTeacher(eps=0.3, seed=0, tie="random").answer(tied, RECENT)]
    assert set(coin) == {Answer.FIRST, Answer.SECOND}
    assert two_sided_ok(coin.count(Answer.SECOND), 400, 0.5)
    assert all(a.distinguishable and a.correct is None
               for a in NoisyTeacher(0.3, 0, tie="random").answer(tied, RECENT))
    # B-Pref's rational teacher takes the same option; beyond ties nothing changes.
    untied = truth([0, 1], [0, 2])
    for tie, expected in (("equal", Answer.EQUAL), ("first", Answer.FIRST)):
        a = bpref(tie=tie).answer([tied[0], untied], RECENT)
        assert [x.choice for x in a] == [expected, Answer.SECOND]
    with pytest.raises(ValueError, match="unknown teacher.tie 'last'; valid: equal, random"):
        NoisyTeacher(eps=0.3, seed=0, tie="last")
    with pytest.raises(ValueError, match="teacher.tie"):
        make_teacher(TeacherConfig(tie="coin"), 0, 2, 10)


def test_noisy_inside_band_is_a_fair_coin():
    t = NoisyTeacher(eps=0.3, seed=1)
    n = 1000
    # |100 - 101| = 1 < 0.3 * 100; segment 1 is truly better.
    out = t.answer([truth([0, 0], [1, 1], 100.0, 101.0)] * n, RECENT)
    assert all(not a.distinguishable for a in out)
    assert {a.choice for a in out} == {Answer.FIRST, Answer.SECOND}
    n_second = sum(a.choice is Answer.SECOND for a in out)
    assert 0.45 * n <= n_second <= 0.55 * n
    # A random label is correct exactly when it happens to match the segment sums.
    assert all(a.correct == (a.choice is Answer.SECOND) for a in out)


def test_noisy_inside_band_with_tied_segments_has_no_correctness():
    t = NoisyTeacher(eps=0.3, seed=0)
    out = t.answer([truth([1, 1], [1, 1], 100.0, 101.0)] * 20, RECENT)
    assert all(a.choice in (Answer.FIRST, Answer.SECOND) and a.correct is None for a in out)


def test_noisy_boundary_is_distinguishable():
    t = NoisyTeacher(eps=0.5, seed=0)
    # |0 - 50| == 0.5 * 100 exactly: not strictly inside the band.
    out = t.answer([truth([0, 0], [1, 1], 0.0, 50.0)] * 50, RECENT)
    assert all(a == TeacherAnswer(Answer.SECOND, True, True) for a in out)
    # Just inside: random.
    inside = t.answer([truth([0, 0], [1, 1], 0.0, 49.999)] * 50, RECENT)
    assert all(not a.distinguishable for a in inside)


def test_noisy_eps_zero_is_ideal():
    t = NoisyTeacher(eps=0.0, seed=0)
    out = t.answer([truth([0, 0], [1, 1], 5.0, 5.0)] * 50, RECENT)  # identical returns
    assert all(a == TeacherAnswer(Answer.SECOND, True, True) for a in out)


def test_noisy_without_recent_returns_nothing_is_in_the_band():
    t = NoisyTeacher(eps=0.9, seed=0)
    out = t.answer([truth([2, 2], [1, 1], 5.0, 5.1)] * 20, [])
    assert all(a == TeacherAnswer(Answer.FIRST, True, True) for a in out)


def test_noisy_negative_returns_use_absolute_average():
    t = NoisyTeacher(eps=0.3, seed=0)
    assert t.threshold([-100.0] * 10) == pytest.approx(30.0)
    out = t.answer([truth([0, 0], [1, 1], -100.0, -101.0)] * 20, [-100.0] * 10)
    assert all(not a.distinguishable for a in out)


def test_noisy_uses_only_last_ten_returns():
    t = NoisyTeacher(eps=0.5, seed=0)
    recent = [1e6] * 10 + [100.0] * 10  # wild early returns must be ignored
    assert t.threshold(recent) == pytest.approx(50.0)
    [out_band] = t.answer([truth([0, 0], [1, 1], 0.0, 49.0)], recent)
    [in_view] = t.answer([truth([0, 0], [1, 1], 0.0, 51.0)], recent)
    assert not out_band.distinguishable
    assert in_view.distinguishable
    # Fewer than ten: the mean of what there is.
    assert t.threshold([40.0, 60.0]) == pytest.approx(25.0)


def _band_queries(n: int = 200) -> list[QueryTruth]:
    return [truth([0, 0], [1, 1], 100.0, 101.0)] * n


def test_noisy_same_seed_same_answers_different_seed_differs():
    a = NoisyTeacher(0.3, seed=7).answer(_band_queries(), RECENT)
    b = NoisyTeacher(0.3, seed=7).answer(_band_queries(), RECENT)
    c = NoisyTeacher(0.3, seed=8).answer(_band_queries(), RECENT)
    assert a == b
    assert [x.choice for x in a] != [x.choice for x in c]


def test_noisy_stream_does_not_depend_on_outcomes():
    # Distinguishable queries still consume their draw: the band answers that follow are the
    # same whether the earlier queries were in the band or not.
    clear = [truth([0, 0], [1, 1], 0.0, 100.0)] * 30
    t1, t2 = NoisyTeacher(0.3, seed=3), NoisyTeacher(0.3, seed=3)
    t1.answer(clear, RECENT)
    t2.answer(_band_queries(30), RECENT)
    assert t1.answer(_band_queries(), RECENT) == t2.answer(_band_queries(), RECENT)


def test_noisy_state_dict_round_trip():
    t = NoisyTeacher(0.3, seed=5)
    t.answer(_band_queries(17), RECENT)
    state = t.state_dict()
    expected = t.answer(_band_queries(), RECENT)
    resumed = NoisyTeacher(0.3, seed=999)
    resumed.load_state_dict(state)
    assert resumed.answer(_band_queries(), RECENT) == expected
    with pytest.raises(ValueError, match="bpref"):
        bpref().load_state_dict(state)


# ---------------------------------------------------------------------------------------------
# BPrefTeacher. segment_length 2, episode_length 10, returns 100 -> margin 20.


def test_bpref_margin_scales_episode_return_to_segment():
    t = bpref(segment_length=50, episode_length=1000)
    assert t.margin([1e6] * 5 + [200.0] * 10) == pytest.approx(10.0)


def test_bpref_skip_threshold():
    t = bpref(eps_skip=0.5)  # thres_skip = 10
    out = t.answer([truth([4, 5], [1, 2]), truth([5, 5], [1, 2]), truth([0, 0], [6, 4])], RECENT)
    assert out[0] == TeacherAnswer(Answer.SKIP, False, None)  # max sum 9 < 10
    assert out[1] == TeacherAnswer(Answer.FIRST, True, True)  # max sum 10: not skipped
    assert out[2] == TeacherAnswer(Answer.SECOND, True, True)
    assert choice_target(out[0].choice) is None


def test_bpref_equal_threshold():
    t = bpref(eps_equal=0.1)  # thres_equal = 2
    out = t.answer([truth([5, 5], [6, 5.5]), truth([5, 5], [6, 6])], RECENT)
    assert out[0] == TeacherAnswer(Answer.EQUAL, False, None)  # |diff| 1.5 < 2
    assert out[1] == TeacherAnswer(Answer.SECOND, True, True)  # |diff| 2: a real choice


def test_bpref_knobs_off_never_skip_or_equal():
    out = bpref().answer([truth([0, 0], [0, 1e-9])] * 10, RECENT)
    assert all(a == TeacherAnswer(Answer.SECOND, True, True) for a in out)


def test_bpref_myopic_gamma_changes_the_winner():
    # Segment 0 front-loaded with the larger plain sum; segment 1 back-loaded.
    q = truth([10, 0, 0, 0], [0, 0, 0, 8])
    [plain] = bpref(gamma=1.0).answer([q], RECENT)
    [myopic] = bpref(gamma=0.5).answer([q], RECENT)  # 10 * 0.125 = 1.25 vs 8
    assert plain == TeacherAnswer(Answer.FIRST, True, True)
    # The myopic teacher prefers segment 1, which the plain sums say is wrong.
    assert myopic == TeacherAnswer(Answer.SECOND, True, False)


def test_bpref_rational_is_deterministic_and_ties_are_equal():
    qs = [truth([0, 1], [0, 1.01]), truth([1, 1], [2, 0]), truth([3, 0], [1, 1])]
    a = bpref(seed=0).answer(qs * 50, RECENT)
    b = bpref(seed=1).answer(qs * 50, RECENT)
    assert a == b
    assert [x.choice for x in a[:3]] == [Answer.SECOND, Answer.EQUAL, Answer.FIRST]
    assert a[1].correct is None


def test_bpref_finite_beta_matches_sigmoid():
    beta, n = 0.5, 4000
    t = bpref(beta=beta)
    out = t.answer([truth([0, 0], [1, 1])] * n, RECENT)  # sum1 - sum0 = 2
    p = 1 / (1 + math.exp(-beta * 2))  # ~0.731
    n_second = sum(a.choice is Answer.SECOND for a in out)
    assert two_sided_ok(n_second, n, p)
    assert all(a.distinguishable and a.choice is not Answer.EQUAL for a in out)
    assert sum(a.correct for a in out) == n_second


def test_bpref_mistake_one_flips_every_answer():
    out = bpref(eps_mistake=1.0).answer([truth([0, 0], [1, 1]), truth([2, 0], [0, 1])], RECENT)
    assert out == [
        TeacherAnswer(Answer.FIRST, True, False),
        TeacherAnswer(Answer.SECOND, True, False),
    ]


def test_bpref_mistake_rate():
    n = 4000
    out = bpref(eps_mistake=0.2, seed=3).answer([truth([0, 0], [1, 1])] * n, RECENT)
    flipped = sum(a.choice is Answer.FIRST for a in out)
    assert two_sided_ok(flipped, n, 0.2)
    assert all(a.correct == (a.choice is Answer.SECOND) for a in out)


def test_bpref_state_dict_round_trip_and_seeds():
    qs = [truth([0, 0], [1, 1])] * 100
    t = bpref(beta=0.5, eps_mistake=0.2, seed=4)
    t.answer(qs, RECENT)
    state = t.state_dict()
    expected = t.answer(qs, RECENT)
    resumed = bpref(beta=0.5, eps_mistake=0.2, seed=123)
    resumed.load_state_dict(state)
    assert resumed.answer(qs, RECENT) == expected
    other = bpref(beta=0.5, eps_mistake=0.2, seed=5)
    other.answer(qs, RECENT)
    assert [a.choice for a in other.answer(qs, RECENT)] != [a.choice for a in expected]


def test_bpref_rejects_bad_knobs():
    with pytest.raises(ValueError, match="beta"):
        bpref(beta=-1.0)
    with pytest.raises(ValueError, match="eps_mistake"):
        bpref(eps_mistake=1.5)

"""The teacher-calibration report: its statistics against hand computations, its definitions
(gap over R_avg, outcomes, bins), and a synthetic export with a known eps that the fit
recovers."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest

from labelstats.calibration import (
    calibration_report,
    estimate_r_avg,
    normalised_gap,
    parse_edges,
)
from labelstats.calibration_stats import (
    binomial_test,
    fit_noisy_teacher,
    is_wide,
    likelihood_cut,
    wilson_interval,
    z_value,
)

# -- statistics against hand computations ------------------------------------------------------


def test_the_wilson_interval_matches_the_formula_worked_by_hand() -> None:
    # 8 of 10, z = 1.95996: centre (0.8 + z^2/20) / (1 + z^2/10) = 0.716740,
    # half-width z / (1 + z^2/10) * sqrt(0.016 + z^2/400) = 0.226578
    low, high = wilson_interval(8, 10) or (0, 0)
    assert low == pytest.approx(0.490162, abs=1e-6)
    assert high == pytest.approx(0.943318, abs=1e-6)
    assert wilson_interval(0, 0) is None
    all_right, all_wrong = wilson_interval(10, 10), wilson_interval(0, 10)
    assert all_right is not None and all_wrong is not None
    assert all_right[0] == pytest.approx(0.722467, abs=1e-6) and all_right[1] == 1.0
    assert all_wrong[0] == 0.0 and all_wrong[1] == pytest.approx(0.277533, abs=1e-6)
    assert z_value(0.95) == pytest.approx(1.959964, abs=1e-6)
    with pytest.raises(ValueError):
        wilson_interval(11, 10)


def test_the_binomial_test_is_exact_and_two_sided() -> None:
    # P(X >= 7 | n=10, p=1/2) = (120 + 45 + 10 + 1) / 1024; both tails: 352/1024
    assert binomial_test(7, 10) == pytest.approx(352 / 1024, rel=1e-12)
    assert binomial_test(5, 10) == pytest.approx(1.0)
    assert binomial_test(0, 10) == pytest.approx(2 / 1024, rel=1e-12)
    # Asymmetric p: counts no likelier than P(X=0) = 0.7^3 = 0.343: 0 (0.343), 2 (0.189),
    # 3 (0.027); P(X=1) = 0.441 is likelier.
    assert binomial_test(0, 3, p=0.3) == pytest.approx(0.343 + 0.189 + 0.027, rel=1e-9)
    assert binomial_test(0, 0) == 1.0


def test_the_eps_fit_matches_the_likelihood_worked_by_hand() -> None:
    answers = [(0.1, "wrong"), (0.2, "correct"), (0.4, "correct"), (0.5, "correct")]
    # eps in [0, 0.1]: all outside the band, 3 correct and 1 wrong: lapse = 2*1/4 = 0.5,
    #   log L = 3 log(1 - 0.5/2) + log(0.5/2) = -2.2493
    # eps in (0.1, 0.2]: the wrong answer is a coin flip, log 0.5; the rest are correct, and
    #   the lapse sits at its floor 0.01: 3 log(0.995); log L = -0.7082, the best
    # eps in (0.2, 0.4]: 2 log 0.5 + 2 log 0.995 = -1.3963; (0.4, 0.5]: -2.0844;
    # eps > 0.5: 4 log 0.5 = -2.7726
    fit = fit_noisy_teacher(answers, cut=1.92)
    assert fit.eps == pytest.approx(0.15)
    assert fit.log_likelihood == pytest.approx(math.log(0.5) + 3 * math.log(0.995))
    assert fit.lapse == pytest.approx(0.01) and fit.cant_tell == 0.0
    # Within 1.92 of -0.7082: every range but eps > 0.5 (-2.7726 is 2.06 below).
    assert (fit.eps_low, fit.eps_high) == (0.0, 0.5)
    assert fit.answers == 4
    assert fit_noisy_teacher(answers, cut=2.1).eps_high is None  # now unbounded


def test_cant_tell_answers_mark_the_band_a_labeller_cannot_resolve() -> None:
    # Can't tell below 0.3, correct above: the band is 0.3 wide, whatever the coin says.
    answers = [(g / 100, "unsure") for g in range(30)] + [
        (g / 100, "correct") for g in range(30, 120)]
    fit = fit_noisy_teacher(answers)
    assert fit.eps_low is not None and fit.eps_high is not None
    assert 0.29 <= fit.eps_low and fit.eps_high <= 0.30 + 1e-12
    assert fit.cant_tell == pytest.approx(1.0)
    # A can't-tell inside the band has likelihood cant_tell = 1; above it a guess would be a
    # can't-tell too, so each correct answer there has 1 - lapse (at its floor, 0.01).
    assert fit.log_likelihood == pytest.approx(90 * math.log(1 - 0.01), rel=1e-9)


def test_infinite_gaps_are_always_outside_the_band() -> None:
    # R_avg = 0: the teacher tells every pair apart, so a wrong answer there is a lapse.
    fit = fit_noisy_teacher([(math.inf, "correct")] * 9 + [(math.inf, "wrong")])
    assert fit.eps == 0.0 and fit.eps_high is None  # no finite gap: every eps is alike
    assert fit.lapse == pytest.approx(0.2)
    with pytest.raises(ValueError):
        fit_noisy_teacher([(0.1, "maybe")])


def test_the_cut_is_the_chi_squared_one_only_for_regular_problems() -> None:
    # A teacher that never lapses: the likelihood falls by log 2 per answer inside the band,
    # so the cut must let a few coin flips that came out right sit just inside it.
    cut = likelihood_cut(0.01, 0.0)
    assert 1.92 < cut < 4 * math.log(2)
    assert likelihood_cut(1.0, 0.0) == pytest.approx(0.0, abs=1e-6)  # all guesses: flat
    assert likelihood_cut(0.01, 0.0) == cut  # a fixed seed: the same interval every time


# -- definitions ---------------------------------------------------------------------------


def row(**values: Any) -> dict[str, Any]:
    """A label row with the columns a report reads; returns 110 vs 90 around R_avg 100."""
    base: dict[str, Any] = {
        "run_id": 1, "round": 0, "algo": "pebble", "query_id": 1, "labeller_id": 1,
        "labeller_name": "ann", "choice": "left", "answer": "first",
        "first_trajectory": 0, "second_trajectory": 1,
        "first_segment_return": 5.0, "second_segment_return": 4.0,
        "first_trajectory_return": 110.0, "second_trajectory_return": 90.0,
    }
    return base | values


def test_r_avg_is_the_mean_of_the_rounds_ten_newest_trajectories() -> None:
    rows = [row(query_id=i, first_trajectory=2 * i, second_trajectory=2 * i + 1,
                first_trajectory_return=float(2 * i), second_trajectory_return=float(2 * i + 1))
            for i in range(8)]  # trajectories 0..15 with returns 0..15
    rows.append(row(round=1, first_trajectory=3, second_trajectory=20,
                    first_trajectory_return=3.0, second_trajectory_return=-7.0))
    estimate = estimate_r_avg(rows)
    assert estimate[(1, 0)] == pytest.approx(sum(range(6, 16)) / 10)  # the newest ten: 6..15
    assert estimate[(1, 1)] == pytest.approx(-2.0)
    assert normalised_gap(110, 90, -100) == pytest.approx(0.2)  # |R_avg|, as the teacher
    assert normalised_gap(1, 1, 0) == math.inf


def test_a_recorded_r_avg_is_used_instead_of_the_estimate() -> None:
    # Returns 110 and 90: the estimate is R_avg 100 (gap 0.2); the trainer recorded 40 (gap 0.5).
    edges = parse_edges("0, 0.3, inf")
    estimated = calibration_report([row()], edges=edges).everyone.bins
    recorded = calibration_report([row(r_avg=40.0)], edges=edges).everyone.bins
    assert [b.rates.answers for b in estimated] == [1, 0]
    assert [b.rates.answers for b in recorded] == [0, 1]


def test_outcomes_bins_and_rates_follow_the_definitions() -> None:
    rows = [
        row(query_id=1),  # correct, gap 0.2
        row(query_id=2, choice="right", answer="second"),  # wrong
        row(query_id=3, choice="cant_tell", answer="cant_tell"),  # can't tell
        row(query_id=4, choice="equal", answer="equal"),  # unequal returns: can't tell
        row(query_id=5, choice="equal", answer="equal",  # equal segments: correct
            second_segment_return=5.0),
        row(query_id=6, choice="skip", answer="skip"),  # counted, judged nowhere
        row(query_id=7, choice="left", answer="second",  # gap 1.0: correct
            first_trajectory_return=50.0, second_trajectory_return=150.0,
            first_segment_return=1.0, second_segment_return=2.0),
        row(query_id=8, first_segment_return=None),  # no ground truth: left out
    ]
    report = calibration_report(rows, edges=parse_edges("0, 0.5, inf"))
    # R_avg: the newest ten trajectories the round shows are 0 and 1; the returns stored last
    # under an index count: 50 and 150, so R_avg = 100.
    everyone = report.everyone.rates
    assert (report.rows, report.without_truth) == (8, 1)
    assert (everyone.answers, everyone.skipped) == (7, 1)
    assert (everyone.correct, everyone.wrong, everyone.cant_tell) == (3, 1, 2)
    assert everyone.match_ratio == pytest.approx(3 / 4)
    assert everyone.cant_tell_rate == pytest.approx(2 / 6)
    low, high = report.everyone.bins
    assert (low.low, low.high, high.low, high.high) == (0.0, 0.5, 0.5, None)
    assert (low.rates.answers, low.rates.correct, low.rates.wrong, low.rates.cant_tell) == (
        6, 2, 1, 2)
    assert (high.rates.answers, high.rates.correct) == (1, 1)
    assert low.rates.match_low == pytest.approx(wilson_interval(2, 3)[0])  # type: ignore[index]
    # Position: left on queries 1 and 7 (the row without truth is left out), right on 2.
    position = report.everyone.position
    assert (position.left, position.right) == (2, 1)
    assert position.p_value == pytest.approx(1.0)
    [pebble] = report.algos
    assert (pebble.runs, pebble.queries, pebble.rates.answers) == (1, 7, 7)
    assert report.edges == [0.0, 0.5, None]


def test_gold_and_practice_answers_are_left_out_of_the_algorithms_numbers() -> None:
    """Gold and practice pairs are known-answer pairs far apart by construction, not the
    algorithm's queries: counted in, they would lift its match ratio, its median gap and the
    fitted eps of everyone who answered them (the labeller quality table scores them apart)."""
    own = [row(query_id=q, r_avg=100.0, first_trajectory_return=100.0,
               second_trajectory_return=99.0,
               **({} if q % 2 else {"choice": "right", "answer": "second"}))
           for q in range(10)]  # gap 0.01, right half the time
    known = [row(query_id=100 + q, gold=True, practice=q < 3, r_avg=100.0,
                 first_trajectory_return=100.0, second_trajectory_return=0.0)
             for q in range(10)]  # gap 1, all right
    alone, mixed = calibration_report(own), calibration_report(own + known)
    for report in (alone, mixed):
        [pebble] = report.algos
        assert (pebble.queries, pebble.rates.answers, pebble.rates.match_ratio) == (10, 10, 0.5)
        assert pebble.median_gap == pytest.approx(0.01)
        [ann] = report.labellers
        assert ann.rates.answers == report.everyone.rates.answers == 10
        assert sum(b.rates.answers for b in report.everyone.bins) == 10
    assert mixed.everyone.fit == alone.everyone.fit
    assert (mixed.rows, mixed.gold_answers, alone.gold_answers) == (20, 10, 0)


def test_a_first_or_second_answer_on_tied_segments_is_no_verdict() -> None:
    """Exactly tied segments have no right side: a first/second answer there is neither right
    nor wrong (the trainer's is_correct gives None), so it cannot pull the match ratio below
    chance inside the band."""
    tied = {"first_segment_return": 0.0, "second_segment_return": 0.0}
    rows = [row(query_id=1),  # correct
            row(query_id=2, **tied),  # first on a tie
            row(query_id=3, choice="right", answer="second", **tied),  # second on a tie
            row(query_id=4, choice="equal", answer="equal", **tied)]  # equal on a tie: correct
    rates = calibration_report(rows).everyone.rates
    assert (rates.answers, rates.no_verdict, rates.skipped) == (4, 2, 0)
    assert (rates.correct, rates.wrong, rates.cant_tell) == (2, 0, 0)
    assert rates.match_ratio == 1.0
    assert calibration_report(rows).everyone.fit.answers == 2  # the fit reads judged answers


def test_an_eps_fit_whose_interval_is_wider_than_eps_is_flagged() -> None:
    assert is_wide(0.118, 0.110, 0.363) and is_wide(0.3, 0.2, None)
    assert not is_wide(0.3, 0.25, 0.4) and not is_wide(0.0, 0.0, 0.04)
    # Teachers with eps 0.3 and exact answers outside the band, on many gaps: a narrow interval.
    gaps = [i / 100 for i in range(150)]
    sharp = fit_noisy_teacher([(g, "correct" if g >= 0.3 else ("wrong" if i % 2 else "correct"))
                               for i, g in enumerate(gaps)])
    assert sharp.eps_low is not None and sharp.eps_low <= 0.3 and not sharp.wide
    few = fit_noisy_teacher([(0.1, "correct"), (0.5, "correct"), (0.2, "wrong")])
    assert few.wide


def test_rows_without_the_needed_columns_and_bad_bins_are_refused() -> None:
    with pytest.raises(ValueError, match="lack the columns .*labeller_id"):
        calibration_report([{k: v for k, v in row().items() if k != "labeller_id"}])
    for text, why in [("0.1,0.5", "first edge must be 0"), ("0,0.5,0.2", "increase"),
                      ("0", "2 to"), ("0,a", "not a comma-separated"), ("0,nan", "first")]:
        with pytest.raises(ValueError, match=why):
            parse_edges(text)
    assert calibration_report([]).everyone.fit.eps is None  # no rows: an empty report


# -- a synthetic export with a known eps --------------------------------------------------------


def synthetic_rows(eps: float, n: int, seed: int, *, lapse: float = 0.0,
                   cant_tell: float = 0.0) -> list[dict[str, Any]]:
    """n answers of one noisy-teacher labeller: gaps uniform in [0, 1.2] R_avg, R_avg = 100."""
    rng = random.Random(seed)
    rows = []
    for i in range(n):
        gap = rng.uniform(0.0, 1.2) * 100.0
        better_first = rng.random() < 0.5
        first, second = (100 + gap / 2, 100 - gap / 2) if better_first else (
            100 - gap / 2, 100 + gap / 2)
        guess = gap < eps * 100.0 or rng.random() < lapse
        if guess and rng.random() < cant_tell:
            preferred = None
        elif guess:
            preferred = "first" if rng.random() < 0.5 else "second"
        else:
            preferred = "first" if better_first else "second"
        left_is_first = rng.random() < 0.5
        choice = "cant_tell" if preferred is None else (
            "left" if (preferred == "first") == left_is_first else "right")
        rows.append(row(query_id=i, first_trajectory=2 * i, second_trajectory=2 * i + 1,
                        first_trajectory_return=first, second_trajectory_return=second,
                        first_segment_return=first / 20, second_segment_return=second / 20,
                        choice=choice, answer=preferred or "cant_tell"))
    return rows


@pytest.mark.parametrize("eps, lapse, cant_tell", [(0.3, 0.0, 0.0), (0.5, 0.1, 0.4)])
def test_a_synthetic_export_gives_back_its_eps(eps: float, lapse: float, cant_tell: float) -> None:
    report = calibration_report(synthetic_rows(eps, 800, seed=7, lapse=lapse, cant_tell=cant_tell))
    [labeller] = report.labellers
    fit = labeller.fit
    assert fit.eps == pytest.approx(eps, abs=0.03)
    assert fit.eps_low is not None and fit.eps_high is not None
    assert fit.eps_low <= eps <= fit.eps_high and fit.eps_high - fit.eps_low < 0.1
    assert fit.lapse == pytest.approx(max(lapse, 0.01), abs=0.05)
    assert fit.cant_tell == pytest.approx(cant_tell, abs=0.1)
    # Inside the band the answers are a coin flip; well outside it, right but for lapses.
    inside = [b for b in labeller.bins if b.high is not None and b.high <= eps - 0.05]
    outside = [b for b in labeller.bins if b.low >= eps + 0.1 and b.rates.answers]
    assert all(abs((b.fitted_match or 0) - 0.5) < 1e-9 for b in inside)
    assert all((b.rates.match_ratio or 0) > 0.85 for b in outside)

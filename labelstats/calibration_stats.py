"""The statistics of the teacher-calibration report, in plain Python (no NumPy, no SciPy).

- `wilson_interval`: a binomial proportion's Wilson score interval.
- `binomial_test`: the exact two-sided binomial test (SciPy's `binomtest` p-value).
- `fit_noisy_teacher`: the eps of the paper's noisy teacher that best reproduces a labeller's
  answers, by maximum likelihood, with a profile-likelihood interval.

The noisy-teacher model (docs/QUALITY.md has it with examples). Each answer has a normalised
gap g (the true return gap over R_avg) and an outcome: correct, wrong, or no preference
(can't tell). An answer comes from one of two mechanisms:

- the teacher: it names the better segment. It is used when g >= eps, with probability 1 - lapse;
- a guess: always when g < eps (the band the labeller cannot resolve), and with probability
  `lapse` when g >= eps. A guess is "can't tell" with probability `cant_tell`, otherwise a fair
  coin between the two segments.

So below the band P(correct) = P(wrong) = (1 - cant_tell) / 2 and P(can't tell) = cant_tell;
above it P(wrong) = lapse (1 - cant_tell) / 2, P(can't tell) = lapse * cant_tell, and the rest is
correct. lapse = cant_tell = 0 is the paper's teacher. `lapse` is at least `LAPSE_MIN`, so no
answer ever has probability zero. For each eps, lapse and cant_tell take their maximum-likelihood
values (coordinate ascent, each step in closed form); the likelihood is then a step function of
eps that changes only at the observed gaps, so it is evaluated once per interval between them.

The interval holds every eps whose profile log-likelihood is within a cut of the best. A step
function of a threshold is not a regular likelihood: the chi-squared cut (1.92 at 95%) covers
the true eps only about 85% of the time in simulation, because a few coin flips just inside the
band that happen to come out right pull the estimate in. So the cut is taken from the fitted
model itself: away from the true eps, the log-likelihood gained by moving eps past each answer
is a random walk with negative drift on either side, and the cut is the `level` quantile of the
larger of the two walks' maxima, simulated (`WALKS` pairs, a fixed seed: the same answers give
the same interval).
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

LAPSE_MIN = 0.01
"""the smallest lapse rate the fit allows: one answer in a hundred may be a slip"""
LEVEL = 0.95
"""the default confidence level of every interval"""
WALKS = 2000
"""random-walk pairs simulated to find the interval's cut"""
_ASCENT_STEPS = 50
_WALK_FLOOR = 15.0  # a walk this far below its maximum never climbs back in practice
_WALK_STEPS = 500


def z_value(level: float = LEVEL) -> float:
    """The standard normal quantile of a two-sided `level` interval (1.96 for 0.95)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"a confidence level must be in (0, 1), got {level}")
    return NormalDist().inv_cdf((1.0 + level) / 2.0)


def wilson_interval(successes: int, n: int, level: float = LEVEL) -> tuple[float, float] | None:
    """The Wilson score interval of successes / n; None when n is 0."""
    if not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return None
    z = z_value(level)
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z / (1 + z2 / n) * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    # The ends are exact at 0 and n successes (rounding would leave them a hair inside).
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == n else min(1.0, centre + half)
    return low, high


def binomial_test(successes: int, n: int, p: float = 0.5) -> float:
    """The exact two-sided p-value of `successes` in `n` trials against probability `p`: the
    total probability of every count no likelier than the observed one (SciPy's rule, with
    its relative tolerance of 1e-7). 1.0 when n is 0."""
    if not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got {successes} of {n}")
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p}")
    if n == 0:
        return 1.0

    def log_pmf(k: int) -> float:
        return (math.lgamma(n + 1) - math.lgamma(k + 1) - math.lgamma(n - k + 1)
                + k * math.log(p) + (n - k) * math.log1p(-p))

    observed = log_pmf(successes) + math.log1p(1e-7)
    total = math.fsum(math.exp(lp) for lp in map(log_pmf, range(n + 1)) if lp <= observed)
    return min(1.0, total)


@dataclass(frozen=True)
class EpsFit:
    """The noisy teacher that best reproduces a set of answers."""

    eps: float | None
    """the maximum-likelihood eps: the middle of the range of eps with the highest likelihood
    (its lower end when that range is unbounded); None without answers"""
    eps_low: float | None
    """the lower end of the profile-likelihood interval"""
    eps_high: float | None
    """its upper end; None when unbounded (every eps above eps_low explains the answers)"""
    log_likelihood: float | None
    """the log-likelihood of the answers under the fitted teacher (natural log)"""
    lapse: float | None
    """the fitted share of guesses on pairs outside the band"""
    cant_tell: float | None
    """the fitted share of guesses answered "can't tell" rather than by a coin"""
    answers: int
    """answers the fit used (correct, wrong or can't tell)"""
    level: float
    """the interval's confidence level"""
    wide: bool = False
    """the interval is unbounded or wider than eps itself: the answers hardly pin eps down, so
    read the interval, not the point"""


def is_wide(eps: float, low: float, high: float | None) -> bool:
    """Whether an eps interval is too wide for its point estimate to mean much."""
    return high is None or high - low > max(eps, WIDE_FLOOR)


WIDE_FLOOR = 0.05
"""an interval narrower than this is never called wide (eps near 0 has a tiny point value)"""


@dataclass(frozen=True)
class _Counts:
    correct: int = 0
    wrong: int = 0
    unsure: int = 0

    @property
    def n(self) -> int:
        return self.correct + self.wrong + self.unsure

    def plus(self, other: _Counts) -> _Counts:
        return _Counts(self.correct + other.correct, self.wrong + other.wrong,
                       self.unsure + other.unsure)

    def minus(self, other: _Counts) -> _Counts:
        return _Counts(self.correct - other.correct, self.wrong - other.wrong,
                       self.unsure - other.unsure)


def _xlogy(x: float, y: float) -> float:
    return 0.0 if x == 0 else x * math.log(y)


def _log_likelihood(below: _Counts, above: _Counts, lapse: float, cant_tell: float) -> float:
    coin = (1.0 - cant_tell) / 2.0
    return (
        _xlogy(below.correct + below.wrong, coin) + _xlogy(below.unsure, cant_tell)
        + _xlogy(above.correct, 1.0 - lapse + lapse * coin)
        + _xlogy(above.wrong, lapse * coin) + _xlogy(above.unsure, lapse * cant_tell)
    )


def _best_lapse(above: _Counts, cant_tell: float) -> float:
    n = above.correct + above.wrong + above.unsure
    if n == 0:
        return LAPSE_MIN
    lapse = 2.0 * (above.wrong + above.unsure) / ((1.0 + cant_tell) * n)
    return min(1.0, max(LAPSE_MIN, lapse))


def _best_cant_tell(below: _Counts, above: _Counts, lapse: float) -> float:
    # The root in [0, 1] of k(A+T+C)t^2 - (AK + T + Ck)t + TK, the likelihood's derivative in
    # t = cant_tell times t(1-t)(K-kt), where k = lapse/2, K = 1-k, A the coin-like answers
    # (below: correct and wrong; above: wrong), T the can't-tells and C the correct above.
    unsure = below.unsure + above.unsure
    if unsure == 0:
        return 0.0
    coin_like = below.correct + below.wrong + above.wrong
    k = lapse / 2.0
    big = 1.0 - k
    a2 = k * (coin_like + unsure + above.correct)
    a1 = -(coin_like * big + unsure + above.correct * k)
    a0 = unsure * big
    root = 2.0 * a0 / (-a1 + math.sqrt(max(0.0, a1 * a1 - 4.0 * a2 * a0)))
    return min(1.0, max(0.0, root))


def _profile(below: _Counts, above: _Counts, cant_tell: float) -> tuple[float, float, float]:
    """(log-likelihood, lapse, cant_tell) at their best for this split, from `cant_tell`."""
    lapse = _best_lapse(above, cant_tell)
    for _ in range(_ASCENT_STEPS):
        new_cant_tell = _best_cant_tell(below, above, lapse)
        new_lapse = _best_lapse(above, new_cant_tell)
        done = abs(new_cant_tell - cant_tell) < 1e-12 and abs(new_lapse - lapse) < 1e-12
        cant_tell, lapse = new_cant_tell, new_lapse
        if done:
            break
    return _log_likelihood(below, above, lapse, cant_tell), lapse, cant_tell


def _outcome_probabilities(lapse: float, cant_tell: float) -> tuple[list[float], list[float]]:
    """P(correct, wrong, unsure) below the band and above it."""
    coin = (1.0 - cant_tell) / 2.0
    below = [coin, coin, cant_tell]
    above = [1.0 - lapse + lapse * coin, lapse * coin, lapse * cant_tell]
    return below, above


def _walk_maximum(rng: random.Random, draw: list[float], steps: list[float],
                  length: int) -> float:
    """The largest partial sum (0 included) of `length` steps `steps[o]`, with outcomes o
    drawn from `draw`."""
    first, second = draw[0], draw[0] + draw[1]
    position = peak = 0.0
    for _ in range(length):
        u = rng.random()
        position += steps[0] if u < first else steps[1] if u < second else steps[2]
        if position > peak:
            peak = position
        elif position < peak - _WALK_FLOOR:
            break
    return peak


def likelihood_cut(lapse: float, cant_tell: float, level: float = LEVEL,
                   lengths: tuple[int, int] = (_WALK_STEPS, _WALK_STEPS)) -> float:
    """How far below the best log-likelihood the interval reaches, for a fitted teacher: the
    `level` quantile of the larger maximum of the two random walks of the log-likelihood ratio
    (answers inside the band seen as outside it, and the other way round). `lengths`: how many
    answers each walk can pass (those inside the band, those outside it with a finite gap), at
    most `_WALK_STEPS` each."""
    below, above = _outcome_probabilities(lapse, cant_tell)

    def log_ratio(p: float, q: float) -> float:
        return -math.inf if p == 0 else math.log(p / q) if q > 0 else 0.0

    # Moving eps down past an answer inside the band, and up past one outside it.
    down = [log_ratio(a, b) for a, b in zip(above, below, strict=True)]
    up = [log_ratio(b, a) for a, b in zip(above, below, strict=True)]
    down_length, up_length = (min(n, _WALK_STEPS) for n in lengths)
    if max(down) <= 1e-12 and max(up) <= 1e-12:
        return 1e-9  # neither walk can rise: the likelihood is flat
    rng = random.Random(0x5E1EC7)
    peaks = sorted(
        max(_walk_maximum(rng, below, down, down_length),
            _walk_maximum(rng, above, up, up_length))
        for _ in range(WALKS)
    )
    return max(1e-9, peaks[min(WALKS - 1, math.ceil(level * WALKS) - 1)])


def fit_noisy_teacher(
    answers: Sequence[tuple[float, str]], level: float = LEVEL, cut: float | None = None
) -> EpsFit:
    """Fit eps (with lapse and cant_tell) to `answers`, each (normalised gap, outcome) with
    outcome "correct", "wrong" or "unsure" (can't tell); a gap may be `math.inf` (a pair every
    eps calls distinguishable). The interval holds every eps whose profile log-likelihood is
    within `cut` of the best (default: `likelihood_cut` of the fitted teacher)."""
    z_value(level)  # checks the level
    if not answers:
        return EpsFit(None, None, None, None, None, None, 0, level)
    per_gap: dict[float, _Counts] = {}
    for gap, outcome in answers:
        if not gap >= 0:
            raise ValueError(f"a normalised gap must be >= 0, got {gap}")
        one = {"correct": _Counts(1, 0, 0), "wrong": _Counts(0, 1, 0),
               "unsure": _Counts(0, 0, 1)}.get(outcome)
        if one is None:
            raise ValueError(f"unknown outcome {outcome!r}: correct, wrong or unsure")
        per_gap[gap] = per_gap.get(gap, _Counts()).plus(one)
    total = _Counts()
    for counts in per_gap.values():
        total = total.plus(counts)
    gaps = sorted(g for g in per_gap if math.isfinite(g))
    # Interval i holds the eps for which the answers at gaps[:i] are below the band:
    # [0, gaps[0]] for i = 0, (gaps[i-1], gaps[i]] after, (gaps[-1], inf) for the last.
    lows = [0.0, *gaps]
    highs: list[float | None] = [*gaps, None]
    fits = []
    below, cant_tell = _Counts(), 0.0
    for i in range(len(lows)):
        if i:
            below = below.plus(per_gap[gaps[i - 1]])
        fit = _profile(below, total.minus(below), cant_tell)
        cant_tell = fit[2]  # a warm start for the next interval
        fits.append(fit)
    best = max(range(len(fits)), key=lambda i: fits[i][0])
    best_ll, lapse, cant_tell = fits[best]
    if cut is None:  # the walks pass the answers inside the band, or the finite ones outside
        passed = [per_gap[g].n for g in gaps]
        lengths = (sum(passed[:best]), sum(passed[best:]))
        cut = likelihood_cut(lapse, cant_tell, level, lengths)
    inside = [i for i, fit in enumerate(fits) if fit[0] >= best_ll - cut]
    high = highs[best]
    eps = lows[best] if high is None else (lows[best] + high) / 2.0
    eps_low, eps_high = lows[min(inside)], highs[max(inside)]
    return EpsFit(
        eps=eps,
        eps_low=eps_low,
        eps_high=eps_high,
        log_likelihood=best_ll,
        lapse=lapse,
        cant_tell=cant_tell,
        answers=total.n,
        level=level,
        wide=is_wide(eps, eps_low, eps_high),
    )

"""The loop's step predicates: when random actions stop, updates start and recur, and when
work done at episode ends falls due."""

from __future__ import annotations

from trainer.schedule import After, Every, Period, Until


def test_until_holds_below_its_step_and_after_holds_past_it():
    assert [Until(3)(s) for s in range(5)] == [True, True, True, False, False]
    assert [After(3)(s) for s in range(5)] == [False, False, False, False, True]
    assert not any(Until(0)(s) for s in range(3))


def test_every_fires_at_multiples_and_never_when_zero():
    assert [s for s in range(1, 13) if Every(4)(s)] == [4, 8, 12]
    assert not any(Every(0)(s) for s in range(1, 13))


def test_a_period_counts_from_when_it_last_happened_not_from_multiples():
    period = Period(10)
    assert [period.due(s) for s in (9, 10)] == [False, True]
    period.happened(13)  # an episode end past the period
    assert [period.due(s) for s in (22, 23)] == [False, True]
    assert not Period(0).due(10**6)

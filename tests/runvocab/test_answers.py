"""Several labellers' answers to one query become the one answer the reward model trains on."""

from __future__ import annotations

import pytest

from runvocab.answers import (
    Answer,
    Click,
    aggregate,
    answer_of_click,
    click_of_answer,
    trained_answer,
)

F, S, E, C, K = Answer.FIRST, Answer.SECOND, Answer.EQUAL, Answer.CANT_TELL, Answer.SKIP


@pytest.mark.parametrize(
    ("answers", "expected"),
    [
        ([F, F, S], F),  # three labellers, 2-1
        ([S, F, S], S),
        ([F, S], C),  # a 1-1 tie is no answer
        ([F, S, E], C),  # a three-way tie too
        ([F, F, S, S, E], C),  # a tie for the most, with a smaller third
        ([E, E, F], E),  # equal wins like any other answer
        ([C, C, F], C),  # can't-tell is more than half
        ([C, C, F, F], F),  # exactly half is not more than half: the decisive ones decide
        ([C, F, F, S], F),
        ([C, F, S], C),  # a tie among the decisive ones
        ([F, K, K, K], F),  # skips are not answers, however many
        ([K, S, K, F, S], S),
        ([K, C, K, F], F),  # one can't-tell of two answers is not more than half
        ([K, K, C], C),
        ([K], K),  # only skips: skip
        ([K, K, K], K),
        ([], K),  # nobody answered
        ([F], F),
        ([C], C),
    ],
)
def test_aggregate_by_hand(answers: list[Answer], expected: Answer) -> None:
    assert aggregate(answers) is expected
    assert aggregate(reversed(answers)) is expected  # order does not matter
    assert aggregate(a.value for a in answers) is expected  # nor whether they are strings


def test_aggregate_refuses_a_word_it_does_not_know() -> None:
    with pytest.raises(ValueError):
        aggregate(["first", "left"])  # a click is not an answer


def test_the_scripted_teachers_answer_is_trained_on_over_peoples() -> None:
    people = [(F, False), (F, False)]
    assert trained_answer(people) is F
    assert trained_answer([*people, (S, True)]) is S  # the teacher answered last: it decides
    assert trained_answer([(K, False), (K, False), ("first", True)]) is F
    assert trained_answer([]) is aggregate([])


@pytest.mark.parametrize("left_is_first", [True, False])
@pytest.mark.parametrize("answer", list(Answer))
def test_a_click_and_its_answer_round_trip(answer: Answer, left_is_first: bool) -> None:
    click = click_of_answer(answer, left_is_first)
    assert isinstance(click, Click)
    assert answer_of_click(click, left_is_first) is answer


def test_the_first_segment_is_the_one_on_the_side_the_server_chose() -> None:
    assert click_of_answer(F, left_is_first=True) is Click.LEFT
    assert click_of_answer(F, left_is_first=False) is Click.RIGHT
    assert click_of_answer(S, left_is_first=False) is Click.LEFT
    assert answer_of_click("right", left_is_first=False) is F

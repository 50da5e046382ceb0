"""Agreement between labellers against hand computations: pairwise agreement, Fleiss' kappa
(Fleiss 1971's worked example, and queries with different numbers of answers), per labeller."""

from __future__ import annotations

import pytest

from labelstats.agreement import agreement, agreement_report

# Fleiss (1971) as Wikipedia works it: 10 subjects, 14 raters, 5 categories; kappa 0.210.
FLEISS = [[0, 0, 0, 0, 14], [0, 2, 6, 4, 2], [0, 0, 3, 5, 6], [0, 3, 9, 2, 0], [2, 2, 8, 1, 1],
          [7, 7, 0, 0, 0], [3, 2, 6, 3, 0], [2, 5, 3, 2, 2], [6, 5, 2, 1, 0], [0, 2, 2, 3, 7]]


def test_fleiss_worked_example() -> None:
    per_query = [[str(j) for j, n in enumerate(row) for _ in range(n)] for row in FLEISS]
    result = agreement(per_query)
    assert (result.queries, result.answers) == (10, 140)
    assert result.fleiss_kappa == pytest.approx(0.20993, abs=1e-5)
    # P-bar: the mean share of agreeing pairs, 0.378 in the worked example.
    assert result.pairwise_agreement == pytest.approx(0.37802, abs=1e-5)


def test_queries_with_different_numbers_of_answers() -> None:
    # q1: 3 answers, 2 agree (2 of 6 ordered pairs); q2: 2 answers that agree (2 of 2).
    # P_i = 1/3 and 1, P-bar = 2/3; p = first 3/5, second 2/5, P_e = 13/25.
    result = agreement([["first", "first", "second"], ["second", "second"], ["first"]])
    assert (result.queries, result.answers) == (2, 5)
    assert result.pairwise_agreement == pytest.approx(4 / 8)
    assert result.fleiss_kappa == pytest.approx((2 / 3 - 13 / 25) / (1 - 13 / 25))


def test_no_shared_query_or_one_category_leaves_kappa_undefined() -> None:
    assert agreement([["first"], ["second"]]).fleiss_kappa is None
    same = agreement([["first", "first"], ["first", "first", "first"]])
    assert same.pairwise_agreement == 1.0 and same.fleiss_kappa is None


def row(query: int, labeller: int, answer: str, **more: object) -> dict[str, object]:
    return {"query_id": query, "run_id": 1, "round": query // 10, "labeller_id": labeller,
            "labeller_name": f"l{labeller}", "answer": answer, "withdrawn_at": None} | more


def test_the_report_leaves_out_skips_and_withdrawn_answers_and_splits_rounds() -> None:
    rows = [row(1, 1, "first"), row(1, 2, "first"), row(1, 3, "second"),
            row(1, 4, "skip"), row(1, 5, "second", withdrawn_at="2026-11-23T12:00:00+00:00"),
            row(11, 1, "cant_tell"), row(11, 2, "cant_tell")]
    report = agreement_report(rows)
    assert (report.everyone.queries, report.everyone.answers) == (2, 5)
    assert [(r.round, r.queries, r.pairwise_agreement) for r in report.rounds] == [
        (0, 1, pytest.approx(1 / 3)), (1, 1, 1.0)]
    by_id = {a.labeller_id: a for a in report.labellers}
    # l1 agrees with l2 on both queries and not with l3: 2 of 3 pairs.
    assert (by_id[1].shared_queries, by_id[1].pairs, by_id[1].agreement) == (
        2, 3, pytest.approx(2 / 3))
    assert by_id[3].agreement == 0.0 and 4 not in by_id and 5 not in by_id

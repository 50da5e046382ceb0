"""Agreement between labellers who answered the same queries.

Made from label rows as the export writes them (`export_rows`, or a file through
`export_read`), so the run page, REST and `sepoa report` agree. Only standing answers count
(not withdrawn), and skips are not answers. The categories are the answers first, second, equal
and cant_tell (`runvocab.answers`).

- Pairwise agreement: of all pairs of answers to one query, the share that are the same.
- Fleiss' κ: agreement beyond what the answers' overall frequencies give by chance. Queries may
  have different numbers of answers: each query with at least two counts with its own share of
  agreeing pairs, P_i = Σ_j n_ij (n_ij − 1) / (n_i (n_i − 1)); P̄ is their mean, p_j the share of
  all those answers in category j, P_e = Σ_j p_j², and κ = (P̄ − P_e) / (1 − P_e). With equal
  numbers of answers this is Fleiss' (1971) κ. None when no query has two answers, or when every
  answer is the same category (P_e = 1).
- Per labeller: the share of their pairs with others' answers to the same queries that agree.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

CATEGORIES = ("first", "second", "equal", "cant_tell")


@dataclass(frozen=True)
class Agreement:
    """Agreement over a set of queries."""

    queries: int
    """queries with at least two answers"""
    answers: int
    """answers to those queries"""
    pairwise_agreement: float | None
    """agreeing pairs of answers over all pairs"""
    fleiss_kappa: float | None


@dataclass(frozen=True)
class RoundAgreement(Agreement):
    run_id: int
    round: int


@dataclass(frozen=True)
class LabellerAgreement:
    labeller_id: int
    labeller_name: str
    shared_queries: int
    """queries this labeller answered that others answered too"""
    pairs: int
    """pairs of this labeller's answer with another's"""
    agreement: float | None
    """the share of those pairs that agree"""


@dataclass(frozen=True)
class AgreementReport:
    everyone: Agreement
    rounds: list[RoundAgreement]
    labellers: list[LabellerAgreement]


def _answer(row: Mapping[str, Any]) -> str | None:
    answer = row.get("answer")
    return answer if answer in CATEGORIES else None


def standing_answers(rows: Iterable[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """The rows that are answers: not withdrawn, not skipped."""
    return [row for row in rows if row.get("withdrawn_at") is None and _answer(row) is not None]


def agreement(per_query: Sequence[Sequence[str]]) -> Agreement:
    """Pairwise agreement and Fleiss' κ of the answers to each query (see the module)."""
    shared = [answers for answers in per_query if len(answers) >= 2]
    if not shared:
        return Agreement(queries=0, answers=0, pairwise_agreement=None, fleiss_kappa=None)
    counts = [Counter(answers) for answers in shared]
    agreeing = sum(n * (n - 1) for c in counts for n in c.values())
    pairs = sum(len(a) * (len(a) - 1) for a in shared)
    p_i = [sum(n * (n - 1) for n in c.values()) / (len(a) * (len(a) - 1))
           for c, a in zip(counts, shared, strict=True)]
    p_bar = sum(p_i) / len(p_i)
    total = sum(len(a) for a in shared)
    overall = Counter(answer for answers in shared for answer in answers)
    p_e = sum((n / total) ** 2 for n in overall.values())
    kappa = None if p_e >= 1.0 else (p_bar - p_e) / (1.0 - p_e)
    return Agreement(queries=len(shared), answers=total, pairwise_agreement=agreeing / pairs,
                     fleiss_kappa=kappa)


def labeller_agreement(rows: Sequence[Mapping[str, Any]]) -> list[LabellerAgreement]:
    """Each labeller's agreement with the others on the queries they share, by labeller id."""
    by_query: dict[int, list[Mapping[str, Any]]] = {}
    for row in rows:
        by_query.setdefault(int(row["query_id"]), []).append(row)
    names: dict[int, str] = {}
    shared: Counter[int] = Counter()
    pairs: Counter[int] = Counter()
    agreeing: Counter[int] = Counter()
    for answers in by_query.values():
        for row in answers:
            me = int(row["labeller_id"])
            names[me] = str(row["labeller_name"])  # the newest name last
            others = [o for o in answers if int(o["labeller_id"]) != me]
            if others:
                shared[me] += 1
                pairs[me] += len(others)
                agreeing[me] += sum(_answer(o) == _answer(row) for o in others)
    return [
        LabellerAgreement(labeller_id=me, labeller_name=names[me], shared_queries=shared[me],
                          pairs=pairs[me],
                          agreement=agreeing[me] / pairs[me] if pairs[me] else None)
        for me in sorted(names)
    ]


def agreement_report(rows: Iterable[Mapping[str, Any]]) -> AgreementReport:
    """Agreement over all the rows' queries, per run and round, and per labeller."""
    answers = standing_answers(rows)
    by_query: dict[int, list[str]] = {}
    round_of: dict[int, tuple[int, int]] = {}
    for row in answers:
        query = int(row["query_id"])
        by_query.setdefault(query, []).append(str(_answer(row)))
        round_of[query] = (int(row["run_id"]), int(row["round"]))
    rounds: dict[tuple[int, int], list[list[str]]] = {}
    for query, given in by_query.items():
        rounds.setdefault(round_of[query], []).append(given)
    return AgreementReport(
        everyone=agreement(list(by_query.values())),
        rounds=[RoundAgreement(run_id=run, round=number, **asdict(agreement(given)))
                for (run, number), given in sorted(rounds.items())],
        labellers=labeller_agreement(answers),
    )

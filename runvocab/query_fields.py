"""A query's fields as they cross the seam, declared once for the trainer, the queue and the export.

A query (a pair of segments) goes from the trainer (`trainer.feedback.Query`) through the
worker (`trainer.queue_hooks.queue_fields`) into the queue (`labelqueue.push_queries`, the `queries`
table) and out again in the export (`labelqueue.export`). Each field that crosses is declared
here once, in `QUERY_FIELDS`: its name in the queue, its type, whether a push may leave it out,
what it means, whether it is provenance, whether the export has it, and the trainer attribute it
is read from. The queue's push validation, the worker's mapping and the export's query columns
are built from this declaration. The `queries` table and its migrations stay written by hand (a
migration is history); a test keeps the table and the declaration equal.

Adding a query field: declare it here, add the column to `labelqueue.models.Query` with a
migration, and, when the trainer makes the value, the attribute to `trainer.feedback.Query`
(with a default, so that older checkpoints still load). The export's column follows; its row in
docs/EXPORT.md is checked by a test that prints the row it expects.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

FieldType = Literal["int", "float", "bool", "str", "floats", "answer", "clip"]
"""a field's type: "floats" is a list of floats (a skill vector); "answer" a
`runvocab.answers.Answer` value; "clip" a clip's storage key, relative to the clips folder"""


@dataclass(frozen=True)
class QueryField:
    """One field of a query, as the trainer, the queue and the export know it."""

    name: str
    """its name in the queue: a pushed key, a `queries` column, an export column"""
    type: FieldType
    description: str
    """what the value means (docs/EXPORT.md's text for an exported field)"""
    optional: bool = False
    """a push may leave it out, and then stores `default`"""
    default: bool | int | None = None
    """what a push that leaves an optional field out stores (None: null)"""
    provenance: bool = False
    """part of what makes a stored query the same pair as a pushed one"""
    exported: bool = True
    """the export has a column of the same name, type and meaning"""
    trainer: str | None = None
    """the `trainer.feedback.Query` attribute the worker reads it from; None when the worker
    adds it itself (the position in the round, the skills, gold pairs) or the queue does later
    (the clips)"""

    @property
    def nullable(self) -> bool:
        """whether the stored value may be null"""
        return self.optional and self.default is None


def _side(side: Literal["first", "second"], index: int) -> tuple[QueryField, ...]:
    return (
        QueryField(f"{side}_trajectory", "int", f"the {side} segment's trajectory index",
                   provenance=True, trainer=f"trajectory{index}"),
        QueryField(f"{side}_start", "int",
                   f"the {side} segment's start step within its trajectory",
                   provenance=True, trainer=f"start{index}"),
        QueryField(f"{side}_skill", "floats", f"the {side} segment's skill vector",
                   optional=True),
        QueryField(f"{side}_clip", "clip", f"storage key of the {side} segment's rendered clip, "
                   "relative to the clips folder", optional=True, exported=False),
    )


QUERY_FIELDS: tuple[QueryField, ...] = (
    QueryField("round", "int", "the feedback round that asked the query", trainer="round"),
    QueryField("position", "int", "the query's index within its round"),
    QueryField("step", "int", "training step at which the query was selected", optional=True,
               trainer="step"),
    QueryField("segment_length", "int", "steps per segment", provenance=True,
               trainer="segment_length"),
    QueryField("rule", "str", "the selection rule that picked the pair", optional=True,
               trainer="rule"),
    *_side("first", 0),
    *_side("second", 1),
    # The trainer always gives the four returns; an external client's pair may come without.
    QueryField("first_segment_return", "float", "ground truth: the first segment's true return",
               optional=True, trainer="segment_return0"),
    QueryField("second_segment_return", "float",
               "ground truth: the second segment's true return", optional=True,
               trainer="segment_return1"),
    QueryField("first_trajectory_return", "float",
               "ground truth: the first segment's whole trajectory's return", optional=True,
               trainer="trajectory_return0"),
    QueryField("second_trajectory_return", "float",
               "ground truth: the second segment's whole trajectory's return", optional=True,
               trainer="trajectory_return1"),
    QueryField("model_p", "float",
               "the reward model's P[second preferred] when the pair was selected",
               optional=True, trainer="model_p"),
    QueryField("score", "float", "the selection score (null for uniform picks)", optional=True,
               trainer="score"),
    QueryField("shadow_choice", "answer", "the run's scripted teacher's answer in segment "
               "terms: first, second, equal, cant_tell or skip", optional=True,
               trainer="shadow_choice"),
    QueryField("distinguishable", "bool", "whether the scripted teacher can tell the pair apart",
               optional=True, trainer="distinguishable"),
    QueryField("r_avg", "float", "R_avg when the pair was selected: the mean return of the run's "
               "newest trajectories (the teacher's `recent_trajectories`); the noisy teacher's "
               "band is eps times its size. Null for queries stored before it was recorded",
               optional=True, trainer="r_avg"),
    QueryField("gold", "bool", "the pair is a gold pair: a known-answer pair that measures "
               "labellers, never trained on (its answer is the segment with the larger true "
               "segment return)", optional=True, default=False),
    QueryField("needs_labels", "int", "distinct labellers' answers wanted: the run's "
               "`feedback.labels_per_query` (the queue gives a gold pair every labeller's)",
               optional=True, default=1, exported=False),
)
"""every field that crosses the seam, in the export's column order"""

QUERY_FIELD_NAMES: tuple[str, ...] = tuple(field.name for field in QUERY_FIELDS)
PROVENANCE: tuple[str, ...] = tuple(field.name for field in QUERY_FIELDS if field.provenance)
"""what makes a stored query the same pair as a pushed one"""

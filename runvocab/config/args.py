"""The command line of a run's configuration: every value field is a flag (`--sac.lr 1e-4`,
also `--sac-lr`), helped by the field's docstring and parsed by `schema.parse_value`; the
common ones also have short aliases (`--eps`, `--selection`, `--budget`, ...)."""

from __future__ import annotations

import argparse
import ast
import functools
import inspect
from collections.abc import Callable
from typing import Any

from runvocab.config import schema
from runvocab.config.schema import leaf_fields, parse_value
from runvocab.names import ConfigError

ALIASES = {
    "eps": "teacher.eps",
    "selection": "feedback.selection",
    "budget": "feedback.budget",
    "per-round": "feedback.per_round",
    "feedback-every": "feedback.every",
    "skills": "skill.backend",
}
OWN_FLAGS = ("task", "preset")
"""fields every command that takes a configuration defines itself"""


@functools.cache  # parses the schema's source: once, not per flag
def field_docs() -> dict[tuple[type, str], str]:
    """Each field's docstring (the string under it, which Python does not keep at run time),
    whitespace folded, by (dataclass, field name)."""
    tree = ast.parse(inspect.getsource(schema))
    docs = {}
    for node in tree.body:
        if not isinstance(node, ast.ClassDef):
            continue
        cls = getattr(schema, node.name)
        for field, doc in zip(node.body, node.body[1:], strict=False):
            if (isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name)
                    and isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)
                    and isinstance(doc.value.value, str)):
                docs[cls, field.target.id] = " ".join(doc.value.value.split())
    return docs


def value_type(path: str) -> Callable[[str], Any]:
    """An argparse `type` for the field at `path`: its error is the one `parse_value` gives."""
    def parse(text: str) -> Any:
        try:
            return parse_value(path, text)
        except ConfigError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    parse.__name__ = f"value of {path}"
    return parse


def add_config_arguments(parser: argparse.ArgumentParser,
                         exclude: tuple[str, ...] = ()) -> None:
    """A flag per value field but task, preset and `exclude` (which a command defines itself)."""
    docs = field_docs()
    for leaf in leaf_fields():
        if leaf.path in (*OWN_FLAGS, *exclude):
            continue
        names = [f"--{leaf.path}"] + [f"--{a}" for a, p in ALIASES.items() if p == leaf.path]
        if "_" in leaf.path:
            names.append(f"--{leaf.path.replace('_', '-')}")
        metavar = getattr(leaf.kind, "__name__", "value").upper()  # tuple[...]: TUPLE
        # argparse formats help with %: a literal one is written %%.
        doc = docs.get((leaf.section, leaf.name), "").replace("%", "%%")
        parser.add_argument(*names, dest=leaf.path, default=None, metavar=metavar, help=doc,
                            type=value_type(leaf.path))


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The fields given on the command line, by dotted path."""
    return {
        leaf.path: getattr(args, leaf.path)
        for leaf in leaf_fields()
        if leaf.path not in OWN_FLAGS and getattr(args, leaf.path, None) is not None
    }

"""The one argument parser of the `sepoa` command, and what its commands share: a user's mistake
is one line on stderr naming the problem and what is valid, with exit status 2, never a
traceback or the whole usage."""

from __future__ import annotations

import argparse
import functools
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NoReturn

ID_MAX = 2**31 - 1
"""the largest id the queue database stores (PostgreSQL's INTEGER)"""
PORT_MAX = 65535


class OneLineParser(argparse.ArgumentParser):
    """An argument error is one line, `sepoa <command>: error: <what is wrong> (see sepoa
    <command> --help)`, exit status 2; sub-commands' parsers are of this class too. A flag of
    type `int` or `float` names what it takes (`'1.5' is not a whole number`), as the typed
    parsers below do."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        kind = kwargs.get("type")
        if kind is int:
            kwargs["type"] = integer()
        elif kind is float:
            kwargs["type"] = real()
        return super().add_argument(*args, **kwargs)


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """`--help` with each flag's default after its help, but for a flag whose default is None
    (its help says what leaving it out means: "the preset's", "<data-dir>/clips when unset"),
    where "(default: None)" would tell nothing."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.default is None:
            return action.help
        return super()._get_help_string(action)


def _bounds(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f": give {low} to {high}"
    if low is not None:
        return f": give at least {low}"
    if high is not None:
        return f": give at most {high}"
    return ""


def integer(what: str = "a whole number", low: int | None = None,
            high: int | None = None) -> Callable[[str], int]:
    """An argparse type: a whole number, within `low` and `high` where given; else one line
    naming the value and the range (`'99999' is not a TCP port: give 1 to 65535`)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or (low is not None and value < low) or \
                (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}{_bounds(low, high)}")
        return value

    parse.__name__ = what
    return parse


def real(what: str = "a number", low: float | None = None,
         high: float | None = None) -> Callable[[str], float]:
    """An argparse type: a finite number, within `low` and `high` where given."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = None
        if value is None or value != value or value in (float("inf"), float("-inf")) or \
                (low is not None and value < low) or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}{_bounds(low, high)}")
        return value

    parse.__name__ = what
    return parse


def environment(name: str, default: str, kind: Callable[[str], Any]) -> Any:
    """The variable `name` (`default` when unset or empty) parsed by the argparse type `kind`;
    ValueError naming the variable, for a command to refuse in one line."""
    text = os.environ.get(name) or default
    try:
        return kind(text)
    except argparse.ArgumentTypeError as err:
        raise ValueError(f"{name}={err}") from None


def database_url_file_argument(p: argparse.ArgumentParser, default: Any = None) -> None:
    """`--database-url-file`, as every command that opens the queue takes it."""
    p.add_argument("--database-url-file", default=default, metavar="FILE",
                   help="a file (mode 600) holding the queue database's URL, to keep a "
                   "password out of commands and scripts (env SEPOA_DATABASE_URL_FILE)")


PORT = integer("a TCP port", 1, PORT_MAX)
RUN_ID = integer("a run id", 1, ID_MAX)


def file_in_the_way(path: str | os.PathLike[str]) -> str | None:
    """The file standing at `path` or at a folder above it, where a folder is to be made;
    None when there is none."""
    here = os.path.abspath(path)
    while not os.path.exists(here) and os.path.dirname(here) != here:
        here = os.path.dirname(here)
    return None if os.path.isdir(here) else here


def fail(message: str) -> int:
    """Print `error: message` on stderr; the exit status of a user's mistake."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def refusing(*errors: type[Exception]) -> Callable[[Callable[[argparse.Namespace], int]],
                                                   Callable[[argparse.Namespace], int]]:
    """A command whose `errors` (raised with a message for the user, such as a database URL
    that cannot be opened) end it in one line with exit status 2."""
    def wrap(run: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
        @functools.wraps(run)
        def guarded(args: argparse.Namespace) -> int:
            try:
                return run(args)
            except errors as err:
                return fail(str(err))

        return guarded

    return wrap


@dataclass(frozen=True)
class Command:
    """One `sepoa` command's arguments and what runs it (its line in `sepoa --help` is in
    `sepoa.cli`). Only the command given is built: its arguments may import what the other
    commands do not need."""

    arguments: Callable[[argparse.ArgumentParser], None]
    """adds the command's flags (and its actions, for a command that has some)"""
    run: Callable[[argparse.Namespace], int]
    """runs the parsed command; returns its exit status"""
    defaults_in_help: bool = field(default=False)
    """whether `--help` shows each flag's default"""

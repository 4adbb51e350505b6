"""The argument parser of every verb: its errors are one line and exit 2, like bad input.

argparse prints its usage text and exits 2 on its own; the command line's contract is one
line naming the option and what was expected (design.md §7), so `Parser.error` raises
`UsageError` (an `InputError`) for `main` to print. argparse also reads a value that starts
with '-' as an option unless it is a plain negative number (`-5`, `-.5`): a range such as
`--clearance-mm -0.05:0.1:3` got "expected one argument". `join_negative_values` rewrites
such a pair to `--clearance-mm=-0.05:0.1:3` before parsing.
"""

from __future__ import annotations

import argparse
import re

from jaxwear._core.errors import InputError


class UsageError(InputError):
    """A command line argparse could not parse (exit 2)."""


class Parser(argparse.ArgumentParser):
    """`ArgumentParser` whose errors raise `UsageError` (one line) instead of exiting."""

    def error(self, message):
        msg = " ".join(str(message).split())  # argparse's messages may wrap
        raise UsageError(f"{self.prog}: {msg} (see `{self.prog} --help`)")


# '-' then a digit or a point, or a signed inf/nan: a value, never an option of ours
_NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d|inf|nan)", re.IGNORECASE)


def value_options(parser: argparse.ArgumentParser) -> set[str]:
    """Option strings (of the parser and its verbs) that take exactly one value."""
    found = set()
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:  # argparse has no public walk over its actions
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())
            elif action.option_strings and action.nargs is None:
                found.update(action.option_strings)
    return found


def join_negative_values(argv: list[str], options: set[str]) -> list[str]:
    """`[--opt, -0.05:0.1:3]` → `[--opt=-0.05:0.1:3]` for options that take a value."""
    out, i = [], 0
    while i < len(argv):
        tok = argv[i]
        if (tok in options and i + 1 < len(argv)
                and _NEGATIVE_VALUE.match(argv[i + 1]) and argv[i + 1] not in options):
            out.append(f"{tok}={argv[i + 1]}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out

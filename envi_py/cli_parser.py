"""The argument parser every envi command line is built from.

The project's rule for bad input is one line naming the problem and exit code 2. argparse's own
errors (a missing option, an invalid choice, ``--epochs 1.5``) print the whole usage block first,
which buries the reason; :class:`EnviParser` prints the reason alone and points to ``--help``.
Subcommands inherit it: ``add_subparsers`` makes sub-parsers of the parent's class.
"""

from __future__ import annotations

import argparse
from typing import Any, NoReturn


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """``--help`` shows each option's default, unless it has none or its text already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            not action.option_strings
            or action.default is None
            or action.default is False
            or action.default == argparse.SUPPRESS
            or "default" in text.lower()
        ):
            return text
        return f"{text} (default: %(default)s)".strip()


class EnviParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr and exit code 2; help shows defaults."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        super().__init__(**kwargs)

    def error(self, message: str) -> NoReturn:
        """``<prog>: error: <message> (see <prog> --help)`` on one line, then exit 2."""
        one_line = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {one_line} (see {self.prog} --help)\n")

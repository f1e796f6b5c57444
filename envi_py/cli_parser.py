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


#: the largest seed: numpy's legacy generators and torch's take up to 2**32 - 1, and an ensemble of
#: K members uses seed..seed+K-1 (a larger one was once torch's "Overflow when unpacking long long")
MAX_SEED = 2**31 - 1


def seed_type(text: str) -> int:
    """``--seed``: a whole number in 0..MAX_SEED, refused by argparse naming the option."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number in 0..{MAX_SEED}, not {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be a whole number in 0..{MAX_SEED}, not {value}")
    return value

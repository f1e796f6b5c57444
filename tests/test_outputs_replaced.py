"""An explicit output (``-o``/``--out``) is the user's request: ``train``, ``verify``, ``check``,
``diagnose`` and ``envi-export`` replace what is there without ``--force``, and each one's ``--help``
says so (a report: replaced as a whole, never mixed with the earlier one's figures or files)."""

from __future__ import annotations

import contextlib
import io

import pytest

from envi_py import export_cli
from envi_py.cli import main


def _option_help(run, argv: list[str], option: str) -> str:
    """The ``--help`` text of ``option`` (its line and the lines continuing it), on one line."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as exc:
        run(argv)
    assert exc.value.code == 0
    lines = out.getvalue().splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.strip().startswith(option))
    block = [lines[start]]
    for ln in lines[start + 1 :]:
        if not ln.startswith(" " * 4) or ln.strip().startswith("-"):
            break
        block.append(ln)
    return " ".join(" ".join(block).split())


@pytest.mark.parametrize(
    "run, argv, option, says",
    [
        (main, ["train", "--help"], "-o OUTPUT, --output", "replaced"),
        (main, ["verify", "--help"], "--out", "replaced as a whole"),
        (main, ["check", "--help"], "--out", "replaced as a whole"),
        (main, ["diagnose", "--help"], "--out", "an earlier diagnosis there is replaced as a whole"),
        (export_cli.main, ["--help"], "-o OUTPUT, --output", "an existing file there is replaced"),
    ],
)
def test_the_help_of_an_output_says_what_is_there_is_replaced(run, argv, option, says):
    assert says in _option_help(run, argv, option)

"""Notes and warnings a command says on standard error, held until its checks have passed.

Bad input gets one line and exit code 2. A note said before the error broke that: a log's pause,
the native engine's fallback or a skipped log came first, the error second, so a user (or a
script reading the last line) saw two or more lines for one mistake. Commands therefore say their
notes through :func:`note`; they are held until the command calls :func:`release` (its checks are
done and the long work begins: the user should see them before a minute of training, not after)
or ends without error. An error drops the held notes, leaving the error line alone. Python
warnings (``--skip-bad``'s skipped logs) take the same path as one line each, not Python's two.
Outside a command (the API, a notebook) notes are said at once.
"""

from __future__ import annotations

import contextlib
import sys
import warnings
from collections.abc import Iterator

_held: list[str] = []
_released = True  # notes are said at once, except inside a command's span before its release


def one_line(text: str) -> str:
    """``text`` as one line, its line breaks shown as ``\\n``. Why: a message names files, and a file
    name may hold a line break; cut at the first one, the error line lost the rest of the name and
    the reason, and printed whole it became two lines for one mistake."""
    return "\\n".join(text.strip().splitlines())


def note(line: str) -> None:
    """Say ``line`` on standard error once the command's checks have passed."""
    if _released:
        print(line, file=sys.stderr, flush=True)
    else:
        _held.append(line)


def release() -> None:
    """The command's checks have passed: say the held notes now, and later ones at once."""
    global _released
    _released = True
    for line in _held:
        print(line, file=sys.stderr)
    _held.clear()
    sys.stderr.flush()


@contextlib.contextmanager
def held_notes(command: str) -> Iterator[None]:
    """A command's span: notes start held, Python warnings become ``<command>: warning: ...``
    notes, and the held ones are said when the block ends without error and dropped when it
    raises (the caller then prints the one error line)."""
    global _released
    _held.clear()
    _released = False

    def show(message: Warning | str, *_: object, **__: object) -> None:
        note(f"{command}: warning: {one_line(str(message)) or message}")

    try:
        with warnings.catch_warnings():
            warnings.showwarning = show
            yield
        release()
    finally:
        _held.clear()
        _released = True

"""SIGTERM and SIGHUP end an envi command the way Ctrl-C does.

Python's default for SIGTERM is to die at once, so the clean-up that Ctrl-C runs never ran: `kill`,
a CI timeout or a closed terminal left `envi simulate`'s hidden staging folder inside ``--out``, a
temporary file beside an export, and `envi-collect`'s current run unrecorded in its ledger. Raising
:class:`Terminated` (a KeyboardInterrupt) from the handler sends both signals down the one path
every command already has for Ctrl-C (``finally`` blocks, staged writes discarded, the partial
run recorded as incomplete). The commands then exit with 128 + the signal number, as a shell
reports a killed command.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType

CAUGHT = (signal.SIGTERM, signal.SIGHUP)


class Terminated(KeyboardInterrupt):
    """Raised in the main thread when the process receives one of :data:`CAUGHT`."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def exit_code(exc: KeyboardInterrupt) -> int:
    """128 + the signal that ended the command: 130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP."""
    return 128 + (exc.signum if isinstance(exc, Terminated) else signal.SIGINT)


def _raise(signum: int, _frame: FrameType | None) -> None:
    raise Terminated(signum)


@contextlib.contextmanager
def signals_interrupt() -> Iterator[None]:
    """Within the block, :data:`CAUGHT` raise :class:`Terminated`; the earlier handlers come back
    after it (a command run in-process, by the tests or a notebook, leaves its host as it was).
    Outside the main thread, where Python cannot set handlers, the block runs unchanged."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    earlier = {sig: signal.signal(sig, _raise) for sig in CAUGHT}
    try:
        yield
    finally:
        for sig, handler in earlier.items():
            signal.signal(sig, handler)

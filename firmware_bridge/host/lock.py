"""One collector per log folder: an OS lock on ``collect.lock`` in it, held for the collector's life.

A second collector on a folder in use would take the first one's live run for a dead collector's
(its ledger entry is unsettled), stop it on the brick and settle it lost, and number its runs
over the first one's. ``flock`` is released by the kernel however its holder ends, ``kill -9``
included, so a collector restarted after a crash is never blocked and settles what the dead one
left, as before. The file stays; its content (the holder's pid) only feeds the refusal message.
"""

from __future__ import annotations

import fcntl
import os
import stat
from pathlib import Path

LOCK_NAME = "collect.lock"


class FolderBusy(Exception):
    """Another collector holds the folder; the message names the folder and that collector's pid."""


def hold(folder: Path) -> int:
    """Lock ``folder`` (made if missing) for this process; the descriptor to close when done.

    Raises :class:`FolderBusy` when another process holds it, having changed nothing in it.
    """
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    try:  # never through a symlink, never a FIFO (opening one would block): a regular file or refused
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
    except OSError as exc:
        raise FolderBusy(f"{path}: cannot use it as the collector's lock ({exc.strerror})") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise FolderBusy(f"{path}: is not a regular file; remove it (envi-collect keeps its lock there)")
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        pid = os.read(fd, 32).decode(errors="replace").strip() or "unknown"  # unknown: it just took it
        os.close(fd)
        raise FolderBusy(
            f"{folder}: another envi-collect (pid {pid}) is recording into it; wait for it or give another --out"
        ) from None
    except OSError:
        os.close(fd)
        raise
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd

"""Writing a file so that no reader ever sees half of it: the one way envi writes what it keeps
(logs and sidecars, manifests, checkpoints, training states, exported models, effect layers).

The content goes to a temporary file in the target's own folder (a rename across file systems
would not be atomic), is flushed to the disk, given the mode any new file gets under the process
umask (a temporary file is created 0600), then renamed over the target. On any failure, Ctrl-C
included, the temporary file is removed and the target is left as it was.
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> Path:
    """Call ``write`` on a binary file that becomes ``path`` once it has returned (its folder is
    made when missing). OSError and anything ``write`` raises propagate, with nothing written.

    A device or FIFO (``-o /dev/null``) is written as it is: renaming a file onto it would replace
    the node itself (as root, /dev/null with a regular file). Through a symbolic link, the file it
    points to is replaced and the link stays."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode  # follows links: what the name leads to
    except OSError:
        mode = None
    if mode is not None and not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        with open(path, "wb") as fh:
            write(fh)
        return path
    if path.is_symlink():
        path = Path(os.path.realpath(path))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name, suffix=".tmp")
    except OSError as exc:  # name the file the user asked for, not a temporary one
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        try:
            os.replace(tmp, path)
        except OSError as exc:  # e.g. a folder in the way: name it, not the temporary file
            raise OSError(exc.errno, exc.strerror, str(path)) from None
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """:func:`atomic_write` of UTF-8 text, line ends as given."""
    return atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))

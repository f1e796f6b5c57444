"""Opening a file the user named: one check and one message for every input envi reads.

A named pipe or a device given where a file is expected would make a reader wait forever (or never
reach the end), and a folder gives an unhelpful IsADirectoryError; so every reader asks here first.
"""

from __future__ import annotations

import json
import math
import os
import stat
import sys
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

#: deepest nesting of lists and objects any JSON or TOML input may have (a sidecar holds 3)
MAX_DEPTH = 32


def regular_file(path: str | os.PathLike, what: str, error: type[ValueError] = ValueError) -> Path:
    """``path`` when it is a regular file (or a link to one); else ``error`` naming it and ``what`` it
    should have been: missing, unreadable, or a pipe, device or folder."""
    path = Path(path)
    try:
        st = path.stat()
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: not a regular file (a pipe, device or folder cannot be {what})")
    return path


def read_text(path: str | os.PathLike, what: str, error: type[ValueError] = ValueError) -> str:
    """A regular file's UTF-8 text (BOM allowed); anything else is ``error`` naming the file."""
    path = regular_file(path, what, error)
    try:
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise error(f"{path}: cannot read {what} ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path}: {what} is not UTF-8 text (byte {exc.start})") from None


def refuse_overwriting(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike], what: str) -> None:
    """A ValueError naming the first of ``outputs`` that is one of ``inputs`` (the same file, by any
    path): ``envi-export m.pt -o m.pt`` or ``envi train -o log_10_0.csv`` once replaced the input
    they read, exit 0. ``what`` names the option the output came from."""
    existing = [Path(p) for p in inputs if p and Path(p).exists()]
    for out in map(Path, outputs):
        if not out.exists():
            continue
        for source in existing:
            if os.path.samefile(out, source):
                raise ValueError(f"{what} {out}: is an input of this command ({source}); nothing overwritten")


def refuse_writing_among_logs(
    outputs: Iterable[str | os.PathLike], logs: Iterable[str | os.PathLike], what: str
) -> None:
    """A ValueError when one of ``outputs`` is a CSV file in the folder of one of ``logs``: ``envi train
    -o logs/m.pt`` once wrote ``logs/m.curves.csv`` there, and every later read of that folder stopped at
    it as a malformed log."""
    folders = {Path(p).resolve().parent for p in logs if p}
    for out in map(Path, outputs):
        if out.suffix.lower() == ".csv" and out.resolve().parent in folders:
            raise ValueError(
                f"{what}: would write {out} among the logs it reads, where later reads of that folder "
                "would take it for a log; save the model in another folder"
            )


def text_name(path: str | os.PathLike, flag: str) -> Path:
    """``path`` when its name is UTF-8 text; else a ValueError showing its bytes escaped. Why: reports,
    sidecars and provenance record output names as text, and a name with a byte that is not UTF-8
    (``m\\xff.pt``) once failed there with a codec message naming no file, the model already saved."""
    path = Path(path)
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        shown = os.fsencode(path).decode("utf-8", "backslashreplace")
        raise ValueError(f"{flag} {shown}: the name is not UTF-8 text; name the output in UTF-8") from None
    return path


def writable_file(path: str | os.PathLike, flag: str) -> Path:
    """``path`` as a file a command will write at the end of its work, refused before the work when
    its name is not text (:func:`text_name`) or its folder cannot be made or written in (a training
    once ran to its end, then failed to save)."""
    path = text_name(path, flag)
    if path.is_dir():
        raise ValueError(f"{flag} {path}: is a folder; name the file to write")
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{flag} {path}: cannot write in {folder} ({exc.strerror or exc})") from None
    return path


def output_folder(path: str | os.PathLike, flag: str = "--out") -> Path:
    """``path`` as a folder a command will write into, refused before any work when a file is there
    (once found only when the report was written, after all the work), or whose name is not text
    (:func:`text_name`)."""
    path = text_name(path, flag)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path}: exists and is not a folder")
    return path


def plain_tree(node: Any, where: str, what: str, error: type[ValueError] = ValueError) -> Any:
    """``node`` (a parsed JSON or TOML tree) when it is at most :data:`MAX_DEPTH` deep and every
    integer in it converts to a float; else ``error`` naming ``where``. Walked without recursion:
    a tree 2,000 levels deep once stopped a command with Python's RecursionError, and a 400-digit
    integer with an OverflowError deep in the code that read it."""
    stack = [(node, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth > MAX_DEPTH:
                raise error(f"{where}: {what} nested deeper than {MAX_DEPTH} levels")
            stack.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item))
        elif isinstance(item, int) and not isinstance(item, bool) and not _fits_float(item):
            raise error(f"{where}: {what} holds an integer too large for a number ({str(item)[:20]}...)")
    return node


def _fits_float(value: int) -> bool:
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


def parse_json(text: str, where: str, what: str, error: type[ValueError] = ValueError) -> Any:
    """``text`` parsed as JSON (NaN refused, ``Infinity`` kept: an open range) and checked by
    :func:`plain_tree`; any failure is one ``error`` naming ``where``."""
    try:
        tree = json.loads(text, parse_constant=_refuse_nan)
    except RecursionError:
        raise error(f"{where}: {what} is not valid JSON (nested too deeply)") from None
    except ValueError as exc:  # syntax, and Python's limit on an integer's digits
        raise error(f"{where}: {what} is not valid JSON ({exc})") from None
    return plain_tree(tree, where, what, error)


def parse_toml(text: str, where: str, what: str, error: type[ValueError] = ValueError) -> dict[str, Any]:
    """``text`` parsed as TOML and checked by :func:`plain_tree`; any failure is one ``error``
    naming ``where``."""
    try:
        tree = tomllib.loads(text)
    except RecursionError:
        raise error(f"{where}: {what} is not valid TOML (nested too deeply)") from None
    except ValueError as exc:  # tomllib.TOMLDecodeError, and Python's limit on an integer's digits
        raise error(f"{where}: {what} is not valid TOML ({exc})") from None
    return plain_tree(tree, where, what, error)


def _refuse_nan(name: str) -> float:
    if name == "NaN":
        raise ValueError("NaN is not a value")
    return float(name)  # Infinity: an open channel range, as write_log records one

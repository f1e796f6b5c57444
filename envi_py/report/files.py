"""The one writer: a report as ``<stem>.md``, ``<stem>.html`` and ``<stem>.json`` side by side.

Figures go into the HTML page itself (base64) and, for the Markdown, into ``<stem>_figures/`` as
PNG files. JSON keeps the command's own payload and gains a ``provenance`` key; non-finite numbers
become null so the file stays strict JSON.

A report replaces the earlier report of its stem as a whole. Everything is written into a hidden
staging folder inside ``out`` first (same file system, so moving in is a rename); only once all of
it is written does it move in, ``<stem>_figures/`` as one folder. So no figure of the earlier report
stays beside the new one, and a failure while writing (a figure that does not render, a full disk,
Ctrl-C) leaves the earlier report as it was, never a torn file or two runs mixed.

A command may hand the writer further files that belong to the report (``envi diagnose``'s retrained
models and fitted layers): they are staged and moved in with it, and the JSON records their names
and sha256 (``attached_files``). The next report of the stem removes a recorded file it does not
write again only while it still holds exactly that content and is not one of the command's inputs:
a file the user put in the folder, or edited, or diagnoses now, is never removed (a file of the
same name as one the new report writes is replaced by it, as the report's own files are).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_write, atomic_write_text
from .document import Figure, Report
from .html import to_html
from .markdown import to_markdown
from .names import safe_name

#: Writes one file that belongs to a report into the folder it is given and returns its path.
Attachment = Callable[[Path], Path]

#: The JSON key listing a report's attachments: what the next report of its stem may remove.
ATTACHED = "attached_files"


@dataclass(frozen=True)
class ReportFiles:
    markdown: Path
    html: Path
    json: Path
    figures: list[Path]
    attachments: list[Path]


def strict(obj: Any) -> Any:
    """``obj`` with NaN and infinities as None (JSON has no NaN), numpy numbers and arrays as Python ones."""
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, np.generic):
        return strict(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    return obj


def _figure_files(report: Report) -> list[tuple[Figure, str]]:
    """Each figure with its PNG file name. Two figures under one file name (``f`` twice, or ``a b``
    and ``a_b``, both ``a_b.png``) are refused: one would silently overwrite the other."""
    files = [(f, f"{safe_name(f.name)}.png") for f in report.figures()]
    names = [n for _, n in files]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"report {report.title!r}: two figures are saved as {dup[0]!r}")
    return files


def _write_staged(
    report: Report, folder: Path, stem: str, attachments: Sequence[Attachment]
) -> tuple[list[str], list[str]]:
    """The whole report in ``folder`` as it will stand in the output folder; the names of its
    figures and of its attachments. The JSON records each attachment with its sha256, so the next
    report removes only a file that is still exactly what this one wrote."""
    fig_dir = f"{stem}_figures"
    files = _figure_files(report)
    for f, name in files:
        atomic_write(folder / fig_dir / name, lambda fh, png=f.png: fh.write(png))
    attached = [attach(folder).name for attach in attachments]
    own = {f"{stem}.md", f"{stem}.html", f"{stem}.json", fig_dir}
    if len(set(attached)) < len(attached) or own & set(attached):
        raise ValueError(f"report {report.title!r}: two of its files are named alike: {', '.join(attached)}")
    atomic_write_text(folder / f"{stem}.md", to_markdown(report, {f.name: f"{fig_dir}/{n}" for f, n in files}))
    atomic_write_text(folder / f"{stem}.html", to_html(report))
    record = [{"name": n, "sha256": _sha256(folder / n)} for n in attached]
    payload = {**report.data, "provenance": report.provenance.to_json(), ATTACHED: record}
    atomic_write_text(folder / f"{stem}.json", json.dumps(strict(payload), indent=1, allow_nan=False))
    return [n for _, n in files], attached


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _stale_attachments(js: Path, keep: set[str], protect: Sequence[Path]) -> list[Path]:
    """The files an earlier report attached that this one does not write again, and that may go: a
    bare name recorded with its sha256 (a JSON of an older writer, or one edited by hand, names
    nothing removable), a regular file still holding exactly that content, and none of ``protect``
    (the command's own inputs: a model kept by an earlier diagnosis may be the one diagnosed now)."""
    try:
        record = json.loads(js.read_text(encoding="utf-8")).get(ATTACHED, [])
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(record, list):
        return []
    guarded = set()
    for p in protect:
        with contextlib.suppress(OSError):
            guarded.add(os.path.realpath(p))
    out = []
    for r in record:
        if not isinstance(r, dict) or not isinstance(r.get("name"), str) or not isinstance(r.get("sha256"), str):
            continue
        name = r["name"]
        path = js.parent / name
        if name in ("", ".", "..") or Path(name).name != name or name in keep or os.path.realpath(path) in guarded:
            continue
        if path.is_file() and not path.is_symlink() and _sha256(path) == r["sha256"]:
            out.append(path)
    return out


class ReportNotRestored(OSError):
    """Moving a new report in failed and undoing it failed too: the earlier files are kept aside."""


def _move_in(staged: Path, out: Path, stem: str, old: Path) -> None:
    """Replace the earlier report by the staged one, by renames only. Each file of the earlier report
    that the new one replaces (and its figures folder, as a whole) first moves into ``old``; on any
    failure or Ctrl-C the renames are undone in reverse, so the earlier report stands as it was. A
    rename is recorded before it is made (a Ctrl-C between the two must not leave it unrecorded) and
    undone only where its result exists. Should undoing fail, :class:`ReportNotRestored` is raised
    and the caller keeps ``old`` (nothing deletes the earlier files)."""
    old.mkdir()
    done: list[tuple[Path, Path]] = []
    try:
        for name in [f"{stem}_figures", *(p.name for p in staged.iterdir() if p.name != f"{stem}_figures")]:
            target = out / name
            if target.exists() or target.is_symlink():
                done.append((target, old / name))
                os.replace(target, old / name)
            if (staged / name).exists():
                done.append((staged / name, target))
                os.replace(staged / name, target)
    except BaseException:
        failed = []
        for src, dst in reversed(done):
            if not (dst.exists() or dst.is_symlink()):
                continue  # recorded, never made
            try:
                os.replace(dst, src)
            except OSError:
                failed.append(src.name)
        if failed:
            raise ReportNotRestored(
                f"{out}: the new report could not be moved in, nor the earlier one fully put back ({', '.join(failed)})"
            ) from None
        raise


def write_files(
    report: Report,
    out: Path,
    stem: str = "report",
    attachments: Sequence[Attachment] = (),
    protect: Sequence[Path] = (),
) -> ReportFiles:
    """Write ``report`` and its ``attachments`` into ``out``, replacing the earlier report of
    ``stem`` as a whole (see the module docstring); ``protect``: files never removed as stale
    attachments (the command's inputs). Raises with the earlier report untouched when any of it
    cannot be written. Two writers into one folder serialise on a lock on it, so the folder holds
    one whole report, the last one, never a mix."""
    out.mkdir(parents=True, exist_ok=True)
    with _locked(out):
        for left in out.glob(f".{stem}.staging-*"):  # a writer killed mid-way; under the lock none is live
            shutil.rmtree(left, ignore_errors=True)
        try:
            staging = Path(tempfile.mkdtemp(dir=out, prefix=f".{stem}.staging-"))
        except OSError as exc:  # name the output folder, not the hidden staging one
            raise OSError(f"{out}: cannot write the report ({exc.strerror or exc})") from None
        keep = False
        try:
            staged = staging / "new"
            staged.mkdir()
            try:
                figures, attached = _write_staged(report, staged, stem, attachments)
            except OSError as exc:
                raise OSError(f"{out}: cannot write the report ({exc.strerror or exc})") from None
            stale = _stale_attachments(out / f"{stem}.json", {p.name for p in staged.iterdir()}, protect)
            try:
                _move_in(staged, out, stem, staging / "old")
            except ReportNotRestored as exc:
                keep = True  # the earlier report's files wait there, out of reach of the next writer's cleanup
                rescued = staging.with_name(staging.name.replace(".staging-", ".unrestored-"))
                os.replace(staging, rescued)
                raise ReportNotRestored(f"{exc}; its files are in {rescued / 'old'}") from None
            except OSError as exc:
                raise OSError(f"{out}: cannot move the new report in ({exc.strerror or exc})") from None
        finally:
            if not keep:
                shutil.rmtree(staging, ignore_errors=True)
        for path in stale:  # only after the new report is in: a failure above keeps the earlier one whole
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    fig_dir = out / f"{stem}_figures"
    return ReportFiles(
        out / f"{stem}.md",
        out / f"{stem}.html",
        out / f"{stem}.json",
        [fig_dir / n for n in figures],
        [out / n for n in attached],
    )


@contextlib.contextmanager
def _locked(folder: Path) -> Iterator[None]:
    """Hold an exclusive flock on the output folder itself while writing (no lock file is left)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)

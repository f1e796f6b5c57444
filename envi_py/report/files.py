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
(``attached_files``). The next report of the stem removes those recorded files it does not write
again, and nothing else: a file the user put in the folder is never touched, whatever its name.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable, Sequence
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
    figures and of its attachments."""
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
    payload = {**report.data, "provenance": report.provenance.to_json(), ATTACHED: attached}
    atomic_write_text(folder / f"{stem}.json", json.dumps(strict(payload), indent=1, allow_nan=False))
    return [n for _, n in files], attached


def _recorded_attachments(js: Path) -> set[str]:
    """The attachments an earlier report recorded in its JSON: bare file names only, so neither a
    JSON the writer did not write nor an edited one can point outside the output folder."""
    try:
        names = json.loads(js.read_text(encoding="utf-8")).get(ATTACHED, [])
    except (OSError, ValueError, AttributeError):
        return set()
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and n not in ("", ".", "..") and Path(n).name == n}


def _move_in(staged: Path, out: Path, stem: str, old: Path) -> None:
    """Replace the earlier report by the staged one, by renames only: the earlier figures folder
    leaves as a whole (into ``old``, removed with the staging folder) before the new one comes in."""
    fig_dir = out / f"{stem}_figures"
    if fig_dir.exists() or fig_dir.is_symlink():
        os.replace(fig_dir, old)
    for p in staged.iterdir():
        os.replace(p, out / p.name)


def write_files(report: Report, out: Path, stem: str = "report", attachments: Sequence[Attachment] = ()) -> ReportFiles:
    """Write ``report`` and its ``attachments`` into ``out``, replacing the earlier report of
    ``stem`` as a whole (see the module docstring). Raises with the earlier report untouched when
    any of it cannot be written."""
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=out, prefix=f".{stem}.staging-"))
    try:
        staged = staging / "new"
        staged.mkdir()
        figures, attached = _write_staged(report, staged, stem, attachments)
        stale = _recorded_attachments(out / f"{stem}.json") - {p.name for p in staged.iterdir()}
        _move_in(staged, out, stem, staging / "old")
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for name in stale:  # only after the new report is in: a failure above keeps the earlier one whole
        if (out / name).is_file() or (out / name).is_symlink():
            (out / name).unlink()
    fig_dir = out / f"{stem}_figures"
    return ReportFiles(
        out / f"{stem}.md",
        out / f"{stem}.html",
        out / f"{stem}.json",
        [fig_dir / n for n in figures],
        [out / n for n in attached],
    )

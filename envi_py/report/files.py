"""The one writer: a report as ``<stem>.md``, ``<stem>.html`` and ``<stem>.json`` side by side.

Figures go into the HTML page itself (base64) and, for the Markdown, into ``<stem>_figures/`` as
PNG files. JSON keeps the command's own payload and gains a ``provenance`` key; non-finite numbers
become null so the file stays strict JSON.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .document import Report
from .html import to_html
from .markdown import to_markdown
from .names import safe_name


@dataclass(frozen=True)
class ReportFiles:
    markdown: Path
    html: Path
    json: Path
    figures: list[Path]


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


def write_files(report: Report, out: Path, stem: str = "report") -> ReportFiles:
    out.mkdir(parents=True, exist_ok=True)
    figures = report.figures()
    fig_dir = out / f"{stem}_figures"
    paths: dict[str, str] = {}
    written: list[Path] = []
    names = [f.name for f in figures]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"report {report.title!r}: two figures are named {dup[0]!r}")
    for f in figures:
        name = safe_name(f.name)
        fig_dir.mkdir(exist_ok=True)
        p = fig_dir / f"{name}.png"
        p.write_bytes(f.png)
        paths[f.name] = f"{fig_dir.name}/{p.name}"
        written.append(p)
    md, page, js = out / f"{stem}.md", out / f"{stem}.html", out / f"{stem}.json"
    md.write_text(to_markdown(report, paths))
    page.write_text(to_html(report), encoding="utf-8")
    payload = {**report.data, "provenance": report.provenance.to_json()}
    js.write_text(json.dumps(strict(payload), indent=1, allow_nan=False))
    return ReportFiles(md, page, js, written)

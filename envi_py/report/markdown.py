"""The same report as Markdown: tables as pipe tables, figures as links to PNG files beside it."""

from __future__ import annotations

from collections.abc import Mapping

from .document import Block, Figure, Report, Table, Text


def _esc(cell: str) -> str:
    return cell.replace("|", "\\|").replace("\n", " ")


def table_markdown(t: Table) -> list[str]:
    lines = [f"**{t.caption}**", ""] if t.caption else []
    lines.append("| " + " | ".join(_esc(c) for c in t.columns) + " |")
    lines.append("|" + "|".join("---:" if j in t.numeric else "---" for j in range(len(t.columns))) + "|")
    lines += ["| " + " | ".join(_esc(v) for v in row) + " |" for row in t.rows]
    return lines


def _block(b: Block, figure_paths: Mapping[str, str]) -> list[str]:
    if isinstance(b, Table):
        return table_markdown(b)
    if isinstance(b, Text):
        return [b.text]
    if isinstance(b, Figure):
        path = figure_paths.get(b.name)
        return [f"![{b.alt or b.caption}]({path})", "", f"*{b.caption}*"] if path else [f"*{b.caption}*"]
    raise TypeError(f"unknown report block {type(b).__name__}")


def to_markdown(report: Report, figure_paths: Mapping[str, str] | None = None) -> str:
    """``figure_paths``: each figure's name -> its file relative to the Markdown file."""
    paths = figure_paths or {}
    lines = [f"# {report.title}", "", *table_markdown(report.verdict), ""]
    for t in report.guide:
        lines += [t.text, ""]
    for s in report.sections:
        lines += [f"## {s.title}", ""]
        for b in s.blocks:
            lines += [*_block(b, paths), ""]
    lines += ["## Provenance", "", *(f"- {k}: {v}" for k, v in report.provenance.items())]
    return "\n".join(lines) + "\n"

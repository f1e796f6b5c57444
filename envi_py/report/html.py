"""One self-contained HTML page: CSS inline, figures embedded as base64 PNG, no script, no network.

The page opens from disk in any browser, can be mailed as one file and prints as it shows.
"""

from __future__ import annotations

import base64
import html
import re

from .document import Block, Figure, Report, Table, Text

CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:2em auto;max-width:1200px;
padding:0 1em;color:#1a1a1a;line-height:1.45}
h1{font-size:1.6em;border-bottom:2px solid #333;padding-bottom:.2em}
h2{font-size:1.25em;margin-top:1.6em;border-bottom:1px solid #bbb}
table{border-collapse:collapse;margin:.6em 0 1.2em;font-size:.9em}
caption{caption-side:top;text-align:left;font-weight:600;padding:.3em 0}
th,td{border:1px solid #ccc;padding:.25em .6em;vertical-align:top}
th{background:#eef1f5;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}
tr:nth-child(even) td{background:#fafafa}
table.verdict th{background:#dfe8f3}
figure{margin:1em 0 1.6em}
figure img{max-width:100%;height:auto;border:1px solid #ddd}
figcaption{font-size:.9em;color:#444;margin-top:.3em}
code{background:#f2f2f2;padding:0 .2em;border-radius:3px}
dl.provenance{display:grid;grid-template-columns:max-content auto;gap:.2em 1em;font-size:.9em}
dl.provenance dt{font-weight:600}
dl.provenance dd{margin:0;word-break:break-all}
.pass{color:#0a6b2d;font-weight:700}.fail{color:#b00020;font-weight:700}.undecided{color:#8a5a00;font-weight:700}
"""

_VERDICT_CLASS = {"PASS": "pass", "FAIL": "fail", "UNDECIDED": "undecided", "n.s.": "undecided", "BEYOND": "fail"}


def _inline(text: str) -> str:
    """Escaped text with `code` spans and **bold** marks rendered."""
    out = html.escape(text)
    out = re.sub(r"`([^`]+)`", r"<code>\1</code>", out)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", out)


def _cell(text: str) -> str:
    word = text.strip("* ")
    cls = _VERDICT_CLASS.get(word.split()[0] if word else "", "")
    inner = _inline(text)
    return f'<span class="{cls}">{inner}</span>' if cls else inner


def table_html(t: Table, css_class: str = "") -> str:
    cls = f' class="{css_class}"' if css_class else ""
    head = "".join(f"<th>{_inline(c)}</th>" for c in t.columns)
    body = "".join(
        "<tr>"
        + "".join(f"<td{' class=num' if j in t.numeric else ''}>{_cell(v)}</td>" for j, v in enumerate(row))
        + "</tr>"
        for row in t.rows
    )
    cap = f"<caption>{_inline(t.caption)}</caption>" if t.caption else ""
    return f"<table{cls}>{cap}<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _block(b: Block) -> str:
    if isinstance(b, Table):
        return table_html(b)
    if isinstance(b, Text):
        return f"<p>{_inline(b.text)}</p>"
    if isinstance(b, Figure):
        data = base64.b64encode(b.png).decode("ascii")
        alt = html.escape(b.alt or b.caption, quote=True)
        return (
            f'<figure><img src="data:image/png;base64,{data}" alt="{alt}">'
            f"<figcaption>{_inline(b.caption)}</figcaption></figure>"
        )
    raise TypeError(f"unknown report block {type(b).__name__}")


def to_html(report: Report) -> str:
    """The whole page; the verdict table is the page's first table, provenance its last section."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(report.title)}</title><style>{CSS}</style></head><body>",
        f"<h1>{html.escape(report.title)}</h1>",
        '<section id="verdict">',
        table_html(report.verdict, "verdict"),
        *(f"<p>{_inline(t.text)}</p>" for t in report.guide),
        "</section>",
    ]
    for s in report.sections:
        parts.append(f"<section><h2>{html.escape(s.title)}</h2>")
        parts += [_block(b) for b in s.blocks]
        parts.append("</section>")
    prov = "".join(f"<dt>{html.escape(k)}</dt><dd>{html.escape(v)}</dd>" for k, v in report.provenance.items())
    parts += ['<section id="provenance"><h2>Provenance</h2>', f'<dl class="provenance">{prov}</dl></section>']
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"

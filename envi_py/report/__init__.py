"""Reports every command writes: one document model, one writer for Markdown, HTML and JSON.

A command builds a :class:`~envi_py.report.document.Report` (verdict table first, then sections of
text, tables and figures, provenance last) and hands it to :func:`~envi_py.report.files.write_files`,
which writes ``<stem>.md``, ``<stem>.html`` (one self-contained page: CSS inline, figures embedded)
and ``<stem>.json`` side by side, replacing the earlier report of that stem as a whole. Nothing
heavy is imported here: matplotlib is imported inside the plotting functions only, so command-line
start-up stays fast.
"""

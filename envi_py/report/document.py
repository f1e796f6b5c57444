"""What a report holds, independent of its file format: a typed document every writer renders.

Order is fixed by the type, so every command's page reads the same way: the title, the verdict table
(the answer), a short reading guide, then sections of evidence (text, tables, figures) and the
provenance last (which model, which envi, which command, when, which system).
"""

from __future__ import annotations

import datetime
import hashlib
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union


@dataclass(frozen=True)
class Table:
    """A table of already formatted cells; ``numeric`` columns are right-aligned."""

    columns: list[str]
    rows: list[list[str]]
    caption: str = ""
    numeric: frozenset[int] = frozenset()

    def __post_init__(self) -> None:
        for r in self.rows:
            if len(r) != len(self.columns):
                raise ValueError(
                    f"table {self.caption or self.columns}: a row has {len(r)} cells, not {len(self.columns)}"
                )


@dataclass(frozen=True)
class Text:
    """A paragraph (plain text; ``code`` spans in backticks are shown as code)."""

    text: str


@dataclass(frozen=True)
class Figure:
    """A rendered picture: PNG bytes, a file name for the Markdown copy, and what it shows."""

    name: str  # file name stem, e.g. "traces_x=30" (made safe by the writer)
    png: bytes
    caption: str
    alt: str = ""


Block = Union[Table, Text, Figure]


@dataclass
class Section:
    title: str
    blocks: list[Block] = field(default_factory=list)


def file_sha256(path: str | Path) -> str | None:
    """The SHA-256 of a file's bytes (None when it cannot be read): which model a report rests on."""
    try:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        return h.hexdigest()
    except OSError:
        return None


@dataclass(frozen=True)
class Provenance:
    """Where a report comes from; ``extra`` holds a command's own settings (alpha, seed, ...)."""

    envi: str
    command: str
    date: str
    system: str | None = None
    model: str | None = None
    model_sha256: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def collect(
        model: str | Path | None = None, system: str | None = None, extra: dict[str, Any] | None = None
    ) -> "Provenance":
        """This process's provenance: envi's version, the command line (as typed, program name
        shortened), the UTC date, and the model file with the hash of its bytes."""
        from .. import __version__

        argv = [Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "envi", *sys.argv[1:]]
        return Provenance(
            envi=__version__,
            command=shlex.join(argv),
            date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            system=system,
            model=None if model is None else str(model),
            model_sha256=None if model is None else file_sha256(model),
            extra=dict(extra or {}),
        )

    def items(self) -> list[tuple[str, str]]:
        """The lines a reader sees, in a fixed order."""
        out = [
            ("model", self.model or "none (this report compares logs only)"),
            ("model sha256", self.model_sha256 or "-"),
            ("envi version", self.envi),
            ("command", self.command),
            ("date (UTC)", self.date),
            ("system description", self.system or "-"),
        ]
        return out + [(k, str(v)) for k, v in self.extra.items()]

    def to_json(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "model_sha256": self.model_sha256,
            "envi": self.envi,
            "command": self.command,
            "date": self.date,
            "system": self.system,
            **self.extra,
        }


@dataclass
class Report:
    """One command's report. ``data`` is the machine-readable payload written as JSON (its format
    is the command's, unchanged; the writer adds a ``provenance`` key)."""

    title: str
    verdict: Table
    provenance: Provenance
    guide: list[Text] = field(default_factory=list)  # how to read the verdict table
    sections: list[Section] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)

    def figures(self) -> list[Figure]:
        return [b for s in self.sections for b in s.blocks if isinstance(b, Figure)]

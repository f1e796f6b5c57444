"""The collector's ledger: one JSON line per run started and one per run settled, in the log folder.

A collector can be killed at any moment (``kill -9``, a crash, a pulled plug), and whatever it had
in memory dies with it. The ledger is what survives: a ``start`` line is on disk (fsynced) before
the brick is told to start, and an ``end`` line once the run's log is written or the run is known
lost. A restarted collector reads it to find the runs an earlier one started but never settled,
to reserve every index ever used (a lost run's file name is never handed to another run), and to
account for every row: ``rows`` recorded + ``rows_lost`` = ``rows_sent`` by the brick.

A line cut by a kill during its own write is skipped when read (the run it described is then
either unsettled, and settled again, or never started); anything else that is not a ledger line is
an error naming the file and the line.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from pathlib import Path
from typing import Any

LEDGER_NAME = "collect-ledger.jsonl"
STATUSES = ("complete", "incomplete", "lost")


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


def _torn(line: str) -> bool:
    """A line a kill cut short: the start of an entry with no end (not foreign text)."""
    return line.startswith('{"event"') and not line.rstrip().endswith("}")


class Ledger:
    """The ledger of one log folder; ``entries`` in file order."""

    def __init__(self, folder: Path) -> None:
        self.path = folder / LEDGER_NAME
        self.entries: list[dict[str, Any]] = self._read() if self.path.exists() else []

    def _read(self) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        try:
            text = self.path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            raise ValueError(f"{self.path}: cannot read the ledger ({exc})") from exc
        for no, line in enumerate(text.splitlines(), start=1):
            if not line.strip() or _torn(line):
                continue
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                raise ValueError(f"{self.path}: line {no}: not a ledger entry") from None
            ok = (
                isinstance(entry, dict)
                and entry.get("event") in ("start", "end")
                and isinstance(entry.get("run_id"), int)
                and isinstance(entry.get("run"), str)
            )
            if not ok or (entry["event"] == "end" and entry.get("status") not in STATUSES):
                raise ValueError(f"{self.path}: line {no}: not a ledger entry (event, run, run_id, status)")
            out.append(entry)
        return out

    def _append(self, entry: dict[str, Any]) -> dict[str, Any]:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a+b") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() > 0:
                fh.seek(-1, os.SEEK_END)
                if fh.read(1) != b"\n":
                    fh.write(b"\n")  # a torn line from a killed writer stays alone on its line
            fh.write(json.dumps(entry).encode() + b"\n")
            fh.flush()
            os.fsync(fh.fileno())
        self.entries.append(entry)
        return entry

    def start(self, run: str, index: int, run_id: int, ticks: int, mode: str) -> dict[str, Any]:
        """Record a run about to be started (before the brick hears of it)."""
        return self._append(
            {
                "event": "start",
                "run": run,
                "index": index,
                "run_id": run_id,
                "ticks": ticks,
                "mode": mode,
                "pid": os.getpid(),
                "at": _now(),
            }
        )

    def end(
        self,
        start: dict[str, Any],
        status: str,
        reason: str,
        rows_sent: int | None,
        rows: int,
        file: str | None,
        settled_by: str = "collector",
    ) -> dict[str, Any]:
        """Record how a run ended; ``rows_lost`` is None when the brick could not say what it sent."""
        if status not in STATUSES:
            raise ValueError(f"run status {status!r} is not one of {', '.join(STATUSES)}")
        lost = None if rows_sent is None else rows_sent - rows
        return self._append(
            {
                "event": "end",
                "run": start["run"],
                "run_id": start["run_id"],
                "status": status,
                "reason": reason,
                "rows_sent": rows_sent,
                "rows": rows,
                "rows_lost": lost,
                "file": file,
                "settled_by": settled_by,
                "at": _now(),
            }
        )

    def unsettled(self) -> list[dict[str, Any]]:
        """Start entries without an end entry: runs an earlier collector started and did not settle."""
        ended = {e["run_id"] for e in self.entries if e["event"] == "end"}
        return [e for e in self.entries if e["event"] == "start" and e["run_id"] not in ended]

    def position(self, run_id: int) -> int | None:
        """Where the run was started in the ledger (its order), None when this ledger never started it."""
        for i, e in enumerate(self.entries):
            if e["event"] == "start" and e["run_id"] == run_id:
                return i
        return None

    def run_ids(self) -> set[int]:
        return {e["run_id"] for e in self.entries}

    def names(self) -> set[str]:
        """Every run name ever started here (each one reserved for good)."""
        return {e["run"] for e in self.entries if e["event"] == "start"}

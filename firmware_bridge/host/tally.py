"""A collector session's account: runs complete / incomplete / lost, and every row sent accounted for.

Built from the ledger's end entries the session wrote (its own runs and the earlier collectors'
runs it settled), so the summary line and the ledger can never disagree.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class Tally:
    complete: int = 0
    incomplete: int = 0
    lost: int = 0
    earlier: int = 0  # of those, runs an earlier collector started and this one settled
    rows: int = 0  # rows recorded in logs
    rows_lost: int = 0  # rows the brick sent that no log holds
    rows_sent: int = 0  # over the runs whose RUN_END said it
    unknown: int = 0  # runs whose sent rows nobody can tell (the brick rebooted or never said)

    def add(self, entry: dict[str, Any]) -> None:
        setattr(self, entry["status"], getattr(self, entry["status"]) + 1)
        self.earlier += entry.get("settled_by") == "next collector"
        self.rows += entry["rows"]
        if entry["rows_sent"] is None:
            self.unknown += 1
        else:
            self.rows_sent += entry["rows_sent"]
            self.rows_lost += entry["rows_lost"]

    @property
    def runs(self) -> int:
        return self.complete + self.incomplete + self.lost

    @property
    def partial(self) -> bool:
        """Anything short of every run complete with every row: the exit code says so."""
        return bool(self.incomplete or self.lost or self.rows_lost or self.unknown)

    def line(self, folder: str) -> str:
        runs = f"{self.complete} complete, {self.incomplete} incomplete, {self.lost} lost run(s) in {folder}"
        if self.earlier:
            runs += f" ({self.earlier} left unsettled by an earlier collector)"
        known = self.rows_sent - self.rows_lost  # recorded rows of the runs whose sent count is known
        rows = f"rows: {known} recorded + {self.rows_lost} lost = {self.rows_sent} sent"
        if self.unknown:
            rows += (
                f"; {self.rows - known} more recorded in {self.unknown} run(s) whose sent rows the brick "
                "could not report"
            )
        return f"{runs}; {rows}"

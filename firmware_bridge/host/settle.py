"""What a collector does on connecting, before its own run: no run of anyone else's goes on.

The brick says in its HANDSHAKE which run it is in. A run still going that this collector did not
just start is an orphan (the collector that started it died, or a cable was pulled mid-run): it is
stopped, and its RUN_END says how many rows the brick sent. Every run the ledger shows started but
never settled is then settled: recovered when its log made it to disk (or only to the staging
name), otherwise reported lost with every row the brick sent for it. The orphan's own frames are
never recorded: the collector that knew its first rows is gone, so its tail alone is not a log.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from envi_py.logs import LogError, read_log, sidecar_path

from ..brick import protocol as P
from .ledger import Ledger
from .link import Link
from .session import BrickError, BrickInfo, stop_run
from .store import finish_staged


@dataclass
class Settlement:
    """What connecting settled: ledger end entries written, and a stopped run no ledger here knows."""

    entries: list[dict[str, Any]]
    foreign: tuple[int, int | None] | None = None  # (run id, rows it sent) of a stranger's run stopped


def _recorded(folder: Path, start: dict[str, Any]) -> tuple[str, str, int] | None:
    """(file, status, rows) of the run's log when it is on disk and is that run's; else None."""
    csv = finish_staged(folder, start["run"]) or folder / f"{start['run']}.csv"
    if not csv.exists() or not sidecar_path(csv).exists():
        return None
    try:
        prov = json.loads(sidecar_path(csv).read_text()).get("provenance", {})
        if prov.get("brick_run_id") != start["run_id"]:
            return None
        rows = len(read_log(csv))
    except (OSError, ValueError, LogError, AttributeError):
        return None
    return csv.name, "complete" if prov.get("complete") else "incomplete", rows


def settle(link: Link, info: BrickInfo, ledger: Ledger, folder: Path) -> Settlement:
    """Stop a run the brick is in, then settle every run the ledger shows unsettled (see module)."""
    unsettled = ledger.unsettled()
    brick_end = None
    waiting = {e["run_id"] for e in unsettled}
    if info.run_state == P.RUN_RUNNING or (info.run_state == P.RUN_ENDED and info.run_id in waiting):
        brick_end = stop_run(link, info.run_id, tries=5)  # an ended run's RUN_END is repeated
        if brick_end is None and info.run_state == P.RUN_RUNNING:
            raise BrickError(f"{link.url}: the brick is in run {info.run_id} and does not stop it when asked")
    foreign = None
    if info.run_state == P.RUN_RUNNING and info.run_id not in ledger.run_ids():
        foreign = (info.run_id, None if brick_end is None else brick_end[3])
    latest = ledger.position(info.run_id) if info.run_state != P.RUN_NONE else None
    entries = []
    for start in unsettled:
        rid = start["run_id"]
        if brick_end is not None and brick_end[0] == rid:
            sent: int | None = brick_end[3]
        elif latest is not None and latest < (ledger.position(rid) or 0):
            sent = 0  # the brick's latest run is older: this one never reached the brick
        else:
            sent = None  # the brick rebooted (or is another brick): it cannot say
        got = _recorded(folder, start)
        if got is None:
            why = "collector died before the brick started it" if sent == 0 else "collector died"
            entries.append(ledger.end(start, "lost", why, sent, 0, None, settled_by="next collector"))
        else:
            file, status, rows = got
            entries.append(
                ledger.end(
                    start, status, "collector died after writing it", sent, rows, file, settled_by="next collector"
                )
            )
    return Settlement(entries, foreign)

"""The size of one validation trial and the default parallelism: light enough for ``--help``.

Kept apart from :mod:`.validate` so the command line can show these defaults without importing
torch and the whole diagnosis.
"""

from __future__ import annotations

import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Size:
    """How big one trial is: logs per role, rows per log, training budget, simulated runs."""

    train: int = 20
    val: int = 5
    diagnose: int = 40
    steps: int = 100
    epochs: int = 150
    lr: float = 5e-4
    history: int = 4
    runs: int = 5


def default_jobs() -> int:
    """Parallel trials: one per core, at most four (each trial trains a model)."""
    return max(1, min(4, os.cpu_count() or 1))

"""The validation's choices and defaults: its world families and procedures, the size of one trial and
the default parallelism, light enough for ``--help``.

Kept apart from :mod:`.validate` so the command line can offer these without importing torch and the
whole diagnosis.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

#: The world families: the one the diagnosis was tuned on first.
WORLDS: tuple[str, ...] = ("steered", "diffdrive")
TUNED_ON = "steered"
#: How a trial trains its model and diagnoses it. ``shipped``: as a user's ``envi train`` and ``envi
#: diagnose`` do (the training defaults: output rounded to the declared resolution and clamped to the
#: observed range, the default model selection; and the staged refit with a Gaussian head when a
#: deterministic model meets runs that vary). ``as-tuned``: as the rules were chosen
#: (:func:`~.validate.validation_training`, no refit), to reproduce the figures measured that way.
PROCEDURES: tuple[str, ...] = ("shipped", "as-tuned")


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

"""The signals of a set of runs by name, and the table of goal metrics over them.

Real logs, simulated traces and twin runs all become one :class:`Runs`: every signal (states,
actions and logged-only columns) as an (R, T) array, the control period and the number of leading
rows never scored (the initial window a simulation copies from its real log).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..logs import Log
from ..system import GoalSpec, LogSchema
from .registry import metric


@dataclass(frozen=True)
class Runs:
    """R runs of T samples: ``signals`` name -> (R, T), ``period_ms`` and ``skip`` leading rows."""

    signals: Mapping[str, np.ndarray]
    period_ms: float
    skip: int = 0

    def __post_init__(self) -> None:
        if not self.signals:
            raise ValueError("runs hold no signals")
        shapes = {name: np.shape(v) for name, v in self.signals.items()}
        first = next(iter(shapes.values()))
        if len(first) != 2 or any(s != first for s in shapes.values()):
            raise ValueError(
                f"every signal must be (runs, samples) of one shape, got "
                f"{', '.join(f'{n} {s}' for n, s in shapes.items())}"
            )
        if isinstance(self.period_ms, bool) or not (math.isfinite(self.period_ms) and self.period_ms > 0):
            raise ValueError(f"period_ms must be a positive number, not {self.period_ms!r}")
        if not 0 <= self.skip < first[1]:
            raise ValueError(f"skipping {self.skip} rows of runs of {first[1]} samples leaves nothing to score")
        for name, values in self.signals.items():
            if not np.isfinite(np.asarray(values, dtype=np.float64)).all():
                raise ValueError(f"signal {name!r} holds NaN or infinite values")

    @property
    def count(self) -> int:
        return int(next(iter(self.signals.values())).shape[0])

    @property
    def scored_length(self) -> int:
        """Samples per run after the skipped rows."""
        return int(next(iter(self.signals.values())).shape[1]) - self.skip

    def scored(self, name: str) -> np.ndarray:
        """Signal ``name`` after the skipped rows, (R, T - skip); an unknown name is an error."""
        if name not in self.signals:
            raise ValueError(f"unknown signal {name!r}; signals: {', '.join(self.signals)}")
        return np.asarray(self.signals[name], dtype=np.float64)[:, self.skip :]


def signals_of(logs: Sequence[Log], schema: LogSchema, skip: int, period_ms: float | None = None) -> Runs:
    """The runs of ``logs`` by signal name, each log cut to the shortest one.

    ``period_ms``: the control period; by default the logs' recorded period (which must agree), else
    the median spacing of their time stamps."""
    if not logs:
        raise ValueError("no logs to evaluate")
    widths = (len(schema.states), len(schema.actions), len(schema.logged))
    for log in logs:
        got = (log.states.shape[1], log.actions.shape[1], log.logged.shape[1])
        if got != widths:
            raise ValueError(
                f"{log.name}: has {got[0]} states, {got[1]} actions, {got[2]} logged columns; "
                f"the schema declares {widths[0]}, {widths[1]}, {widths[2]}"
            )
    t = min(len(log) for log in logs)
    signals: dict[str, np.ndarray] = {}
    for group, channels in (("states", schema.states), ("actions", schema.actions), ("logged", schema.logged)):
        block = np.stack([getattr(log, group)[:t] for log in logs]).astype(np.float64)  # (R, T, k)
        for j, ch in enumerate(channels):
            signals[ch.name] = block[:, :, j]
    return Runs(signals, _period(logs, period_ms), skip)


def _period(logs: Sequence[Log], period_ms: float | None) -> float:
    if period_ms is not None:
        return float(period_ms)
    recorded = {log.meta.period_ms for log in logs if log.meta.period_ms is not None}
    if len(recorded) > 1:
        raise ValueError(f"the logs record different periods ({', '.join(f'{p:g}' for p in sorted(recorded))} ms)")
    if recorded:
        return float(recorded.pop())
    steps = np.concatenate([np.diff(log.time) for log in logs])
    if steps.size == 0:
        raise ValueError("the logs are too short to tell their period")
    return float(np.median(steps))


def goal_values(goal: GoalSpec, runs: Runs) -> np.ndarray:
    """One goal's metric for each run, (R,); errors name the goal."""
    try:
        return metric(goal.metric)(runs.scored(goal.signal), runs.period_ms, **goal.params)
    except ValueError as exc:
        raise ValueError(f"goal {goal.name!r}: {exc}") from None


def goal_table(goals: Sequence[GoalSpec], runs: Runs) -> dict[str, np.ndarray]:
    """Every goal's metric for each run: goal name -> (R,)."""
    return {g.name: goal_values(g, runs) for g in goals}


def goal_scale(goal: GoalSpec, low: float, high: float, scored: int, period_ms: float) -> float | None:
    """The width of the goal metric's possible range for its signal declared on [low, high]
    (None when it cannot be derived: a user's metric or a signal without a finite range)."""
    return metric(goal.metric).scale(low, high, scored, period_ms, goal.params)


def goal_unit(goal: GoalSpec, signal_unit: str) -> str:
    """The goal metric's unit, from its signal's unit."""
    return metric(goal.metric).unit(signal_unit)

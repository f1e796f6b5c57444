"""Shipped sets of goals: ``goals_preset = "lane-keeping"`` gives the paper's eight driving metrics.

The paper scores the lane-keeping robot by episodes of its colour reading above, below and inside a
band around the lane centre (:mod:`envi_py.metrics`). Here each of the eight is a goal metric of
the ``color`` signal with parameters ``centre`` (the controller's threshold, 40 unless the system's
controller says otherwise) and ``band`` (10), computed by :func:`envi_py.metrics.driving_metrics`
itself so the preset and the paper's evaluation can never drift apart. Their scale is the paper's
normalisation (:func:`envi_py.metrics.metric_bounds`).
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any

import numpy as np

from ..metrics import METRIC_NAMES, MetricConfig, driving_metrics, metric_bounds
from ..system import GoalSpec, SystemDescription
from .library import MetricDef

LANE_KEEPING_SIGNAL = "color"
LANE_KEEPING_BAND = 10.0


def _config(centre: float, band: float, low: float = 0.0, high: float = 100.0) -> MetricConfig:
    # skip=0: the trace handed to a goal metric is already cut after the skipped rows
    return MetricConfig(centre=float(centre), band=float(band), skip=0, low=low, high=high)


def _driving_metric(index: int, trace: np.ndarray, centre: float = 40.0, band: float = LANE_KEEPING_BAND) -> np.ndarray:
    return driving_metrics(trace, _config(centre, band))[:, index]


def _driving_scale(index: int, low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float:
    cfg = _config(params.get("centre", 40.0), params.get("band", LANE_KEEPING_BAND), low, high)
    lo, hi = metric_bounds(scored, cfg)
    return float(hi[index] - lo[index])


def _driving_unit(index: int, unit: str) -> str:
    name = METRIC_NAMES[index]
    if name.endswith("_count"):
        return ""
    return "samples" if name.endswith("_duration") else unit


#: The paper's eight metrics by name (``steady_count``, ..., ``under_duration``).
DRIVING: dict[str, MetricDef] = {
    name: MetricDef(
        name,
        partial(_driving_metric, j),
        ("centre", "band"),
        (),
        unit=partial(_driving_unit, j),
        scale=partial(_driving_scale, j),
    )
    for j, name in enumerate(METRIC_NAMES)
}


def lane_keeping_centre(system: SystemDescription | None) -> float:
    """The lane centre: the controller's ``threshold`` parameter when the system declares one, else 40."""
    if system is None or system.controller is None:
        return 40.0
    threshold = system.controller.params.get("threshold", 40.0)
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise ValueError(f"{system.source or system.name}: controller threshold {threshold!r} is not a number")  # noqa: TRY004 (bad input: ValueError)
    return float(threshold)


def preset_goals(name: str, system: SystemDescription | None = None) -> tuple[GoalSpec, ...]:
    """The goals of preset ``name`` for ``system`` (its controller gives the lane centre)."""
    if name != "lane-keeping":
        raise ValueError(f"unknown goals preset {name!r}; known: lane-keeping")
    if system is not None and LANE_KEEPING_SIGNAL not in system.schema.columns:
        raise ValueError(
            f"{system.source or system.name}: goals preset 'lane-keeping' scores the signal "
            f"{LANE_KEEPING_SIGNAL!r}, which this system does not declare"
        )
    centre = lane_keeping_centre(system)
    return tuple(
        GoalSpec(m, m, LANE_KEEPING_SIGNAL, {"centre": centre, "band": LANE_KEEPING_BAND}) for m in METRIC_NAMES
    )


def goals_of(system: SystemDescription) -> tuple[GoalSpec, ...]:
    """All goals of a system: its preset's, then its own declared ones (a name used twice is an error)."""
    goals = (preset_goals(system.preset, system) if system.preset else ()) + tuple(system.goals)
    seen: set[str] = set()
    for g in goals:
        if g.name in seen:
            raise ValueError(f"{system.source or system.name}: goal name {g.name!r} is used twice")
        seen.add(g.name)
    return goals

"""Standard goal metrics of one signal, vectorised over runs.

Every metric takes ``trace`` (R, T): one signal of R runs, already cut after the first ``skip``
rows (the initial window a simulation copies from the real log, so it is never scored), plus its
own keyword parameters; the metrics where time matters also take ``period_ms`` (the control
period). Each returns (R,) floats. Times are in milliseconds and integrals use the rectangle rule
(one sample stands for one period), because logs are sampled once per control period.

The registry :data:`STANDARD` says, for each metric, its parameter names in the order an
expression may give them positionally (``max_abs_dev(color, 40)``), its unit from the signal's unit,
and its *scale*: the size of the metric's possible range, used to put distances between metric
distributions of different signals on one footing (range width for deviations, T*period for
times, 1 for fractions).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

MetricFn = Callable[..., np.ndarray]


@dataclass(frozen=True)
class MetricDef:
    """A goal metric and what a caller needs to use it by name.

    ``params``: parameter names in positional order; ``required``: those without a default.
    ``unit(signal_unit)``: the metric's unit. ``scale(low, high, scored, period_ms, params)``: the
    width of its possible range for a signal declared on [low, high] over ``scored`` samples, or
    None when it cannot be derived (a user's metric: the caller then uses the observed spread).
    """

    name: str
    fn: MetricFn
    params: tuple[str, ...] = ()
    required: tuple[str, ...] = ()
    uses_period: bool = False
    unit: Callable[[str], str] = lambda u: u
    scale: Callable[[float, float, int, float, Mapping[str, Any]], float | None] = (
        lambda low, high, scored, period, params: None
    )

    def __call__(self, trace: np.ndarray, period_ms: float, **params: Any) -> np.ndarray:
        """The metric of each run, with parameters checked by name and the output by shape."""
        unknown = sorted(set(params) - set(self.params))
        if unknown:
            raise ValueError(
                f"metric {self.name!r} has no parameter {unknown[0]!r}; parameters: {', '.join(self.params) or 'none'}"
            )
        missing = [p for p in self.required if p not in params]
        if missing:
            raise ValueError(f"metric {self.name!r} needs parameter {missing[0]!r}")
        trace = np.atleast_2d(np.asarray(trace, dtype=np.float64))
        if trace.ndim != 2 or trace.shape[1] == 0:
            raise ValueError(
                f"metric {self.name!r}: needs (runs, samples) with at least one sample, got shape {trace.shape}"
            )
        if not np.isfinite(trace).all():
            raise ValueError(f"metric {self.name!r}: the signal holds NaN or infinite values")
        out = self.fn(trace, period_ms=period_ms, **params) if self.uses_period else self.fn(trace, **params)
        out = np.asarray(out, dtype=np.float64) if isinstance(out, (np.ndarray, list, tuple)) else out
        if not isinstance(out, np.ndarray) or out.shape != (trace.shape[0],):
            shape = getattr(out, "shape", type(out).__name__)
            raise ValueError(
                f"metric {self.name!r} ({_qualname(self.fn)}) returned {shape}, "
                f"expected one value per run: ({trace.shape[0]},)"
            )
        if np.isnan(out).any():
            raise ValueError(f"metric {self.name!r} ({_qualname(self.fn)}) returned NaN")
        return out


def _qualname(fn: MetricFn) -> str:
    return f"{getattr(fn, '__module__', '?')}:{getattr(fn, '__qualname__', repr(fn))}"


# ---------------------------------------------------------------------- the metrics


def max_abs_dev(trace: np.ndarray, setpoint: float) -> np.ndarray:
    """Largest |signal - setpoint| of each run."""
    return np.abs(trace - setpoint).max(axis=1)


def mean_abs_dev(trace: np.ndarray, setpoint: float) -> np.ndarray:
    """Mean |signal - setpoint| of each run."""
    return np.abs(trace - setpoint).mean(axis=1)


def time_in_band(trace: np.ndarray, setpoint: float, band: float) -> np.ndarray:
    """Fraction of samples with |signal - setpoint| <= band (a fraction in [0, 1], not a time)."""
    return (np.abs(trace - setpoint) <= band).mean(axis=1)


def overshoot(trace: np.ndarray, setpoint: float) -> np.ndarray:
    """Largest excursion above the setpoint, max(signal - setpoint), or 0 if never above."""
    return np.maximum((trace - setpoint).max(axis=1), 0.0)


def undershoot(trace: np.ndarray, setpoint: float) -> np.ndarray:
    """Largest excursion below the setpoint, max(setpoint - signal), or 0 if never below."""
    return np.maximum((setpoint - trace).max(axis=1), 0.0)


def settling_time(trace: np.ndarray, period_ms: float, setpoint: float, band: float) -> np.ndarray:
    """Time (ms) from the first scored sample after which the signal stays within setpoint +- band.

    With k the index of the last sample outside the band, the signal has settled from sample k+1 on:
    the settling time is (k+1)*period; 0 if it never leaves the band, T*period if the last sample is
    still outside (it never settles within the run)."""
    outside = np.abs(trace - setpoint) > band
    t = trace.shape[1]
    last_out = t - 1 - np.argmax(outside[:, ::-1], axis=1)
    return np.where(outside.any(axis=1), (last_out + 1) * period_ms, 0.0)


def rise_time(
    trace: np.ndarray, period_ms: float, low_frac: float = 0.1, high_frac: float = 0.9, setpoint: float | None = None
) -> np.ndarray:
    """Time (ms) the signal takes to go from ``low_frac`` to ``high_frac`` of its change.

    The change is from the first scored sample y0 to the target: ``setpoint`` when given, else the
    run's last sample. The signal has covered a fraction f once (y - y0) * sign(target - y0) >=
    f * |target - y0|. Rise time = (first sample covering high_frac) - (first sample covering
    low_frac), times the period; T*period if it never covers high_frac; 0 when there is no change."""
    if not 0 <= low_frac < high_frac <= 1:
        raise ValueError(f"rise_time needs 0 <= low_frac < high_frac <= 1, got {low_frac}, {high_frac}")
    y0 = trace[:, :1]
    target = trace[:, -1:] if setpoint is None else np.full_like(y0, float(setpoint))
    change = target - y0
    covered = (trace - y0) * np.sign(change)
    size = np.abs(change)
    low_hit, high_hit = covered >= low_frac * size, covered >= high_frac * size
    t = trace.shape[1]
    first_low = np.where(low_hit.any(axis=1), np.argmax(low_hit, axis=1), t)
    first_high = np.where(high_hit.any(axis=1), np.argmax(high_hit, axis=1), t)
    rise = np.where(high_hit.any(axis=1), (first_high - first_low) * period_ms, t * period_ms)
    return np.where(size[:, 0] > 0, rise, 0.0)


def iae(trace: np.ndarray, period_ms: float, setpoint: float) -> np.ndarray:
    """Integral of |signal - setpoint| over the run, sum * period (signal unit x ms)."""
    return np.abs(trace - setpoint).sum(axis=1) * period_ms


def ise(trace: np.ndarray, period_ms: float, setpoint: float) -> np.ndarray:
    """Integral of (signal - setpoint)^2 over the run, sum * period (signal unit^2 x ms)."""
    return ((trace - setpoint) ** 2).sum(axis=1) * period_ms


def oscillations(trace: np.ndarray, setpoint: float) -> np.ndarray:
    """Number of sign changes of signal - setpoint, halved (one full oscillation crosses twice).

    A sample exactly on the setpoint keeps the previous sign, so touching the setpoint and turning
    back is not a crossing."""
    sign = np.sign(trace - setpoint)
    cols = np.arange(sign.shape[1])
    last_nonzero = np.maximum.accumulate(np.where(sign != 0, cols, 0), axis=1)
    held = np.take_along_axis(sign, last_nonzero, axis=1)
    return (held[:, 1:] * held[:, :-1] < 0).sum(axis=1) / 2.0


def minimum(trace: np.ndarray) -> np.ndarray:
    """Smallest value of each run."""
    return trace.min(axis=1)


def maximum(trace: np.ndarray) -> np.ndarray:
    """Largest value of each run."""
    return trace.max(axis=1)


def mean(trace: np.ndarray) -> np.ndarray:
    """Mean value of each run."""
    return trace.mean(axis=1)


def std(trace: np.ndarray) -> np.ndarray:
    """Standard deviation of each run (population form: the run is the whole record)."""
    return trace.std(axis=1)


# ---------------------------------------------------------------------- registry


def _width(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float | None:
    return high - low if math.isfinite(high - low) else None


def _duration(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float:
    return scored * period


def _width_time(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float | None:
    w = _width(low, high, scored, period, params)
    return None if w is None else w * scored * period


def _width2_time(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float | None:
    w = _width(low, high, scored, period, params)
    return None if w is None else w * w * scored * period


def _one(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float:
    return 1.0


def _half_samples(low: float, high: float, scored: int, period: float, params: Mapping[str, Any]) -> float:
    return max((scored - 1) / 2.0, 0.5)


def _ms(unit: str) -> str:
    return "ms"


def _none(unit: str) -> str:
    return ""


def _unit_ms(unit: str) -> str:
    return f"{unit}*ms" if unit else "ms"


def _unit2_ms(unit: str) -> str:
    return f"{unit}^2*ms" if unit else "ms"


STANDARD: dict[str, MetricDef] = {
    m.name: m
    for m in (
        MetricDef("max_abs_dev", max_abs_dev, ("setpoint",), ("setpoint",), scale=_width),
        MetricDef("mean_abs_dev", mean_abs_dev, ("setpoint",), ("setpoint",), scale=_width),
        MetricDef("time_in_band", time_in_band, ("setpoint", "band"), ("setpoint", "band"), unit=_none, scale=_one),
        MetricDef("overshoot", overshoot, ("setpoint",), ("setpoint",), scale=_width),
        MetricDef("undershoot", undershoot, ("setpoint",), ("setpoint",), scale=_width),
        MetricDef("settling_time", settling_time, ("setpoint", "band"), ("setpoint", "band"), True, _ms, _duration),
        MetricDef("rise_time", rise_time, ("low_frac", "high_frac", "setpoint"), (), True, _ms, _duration),
        MetricDef("iae", iae, ("setpoint",), ("setpoint",), True, _unit_ms, _width_time),
        MetricDef("ise", ise, ("setpoint",), ("setpoint",), True, _unit2_ms, _width2_time),
        MetricDef("oscillations", oscillations, ("setpoint",), ("setpoint",), unit=_none, scale=_half_samples),
        MetricDef("min", minimum, scale=_width),
        MetricDef("max", maximum, scale=_width),
        MetricDef("mean", mean, scale=_width),
        MetricDef("std", std, scale=_width),
    )
}

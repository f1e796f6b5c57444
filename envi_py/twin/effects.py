"""The registry of real-world effects the twin can switch on, with parameters and units.

Each effect is recorded, with all its parameters, in every log's metadata when it is on: the twin is
the ground truth against which the sim-to-real diagnosis is scored, so the log must say exactly
which effects made it. Names follow the diagnosis candidates (``envi_py.diagnose.effects``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np


@dataclass(frozen=True)
class Param:
    """One effect parameter: default value, unit, meaning and the range in which it means something
    (``low`` excluded when ``above``; ``whole`` for a count). A value outside it is refused: a NaN
    noise once wrote logs all NaN, an infinite one pinned every reading at the limits."""

    default: float
    unit: str
    doc: str
    low: float = -math.inf
    high: float = math.inf
    above: bool = False
    whole: bool = False

    def rule(self) -> str:
        """The range in words, e.g. 'a whole number from 0 to 1000'."""
        kind = "a whole number" if self.whole else "a number"
        if self.low > -math.inf and self.high < math.inf:
            return f"{kind} from {self.low:g} to {self.high:g}"
        if self.low > -math.inf:
            return f"{kind} {'above' if self.above else 'of at least'} {self.low:g}"
        return f"a finite {kind[2:]}"


#: Ranges shared by several parameters.
_NONNEG = {"low": 0.0}
_POS = {"low": 0.0, "above": True}
_FRACTION = {"low": 0.0, "high": 1.0}
#: a delay in ms, at most an hour: 1e300 once wrote time stamps no reader could take as a period
_DURATION = {"low": 0.0, "high": 3_600_000.0}
_SCALE = {"low": 0.0, "high": 100.0}  # the colour scale
#: a time constant in ms, above 0 and at most an hour: beyond about 1e16 ms a tick's step rounds to
#: nothing and the steering would freeze at its first angle without a word
_TIME_CONSTANT = {"low": 0.0, "above": True, "high": 3_600_000.0}


@dataclass(frozen=True)
class Effect:
    """An effect: what it models and its parameters; ``primary`` takes a bare number (``noise=1.5``)."""

    name: str
    description: str
    params: dict[str, Param]
    primary: str


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect(
            "delay",
            "actuation delay: the commanded angle reaches the steering k ticks later",
            {"ticks": Param(1, "ticks", "delay in control periods", 0.0, 1000.0, whole=True)},
            "ticks",
        ),
        Effect(
            "lag",
            "steering actuator lag: the angle follows the command as a first-order system",
            {"tau_ms": Param(60.0, "ms", "time constant", **_TIME_CONSTANT)},
            "tau_ms",
        ),
        Effect(
            "rate_limit",
            "steering rate limit: the angle moves at most this fast toward the command",
            {"deg_per_s": Param(600.0, "deg/s", "maximum steering speed", **_POS)},
            "deg_per_s",
        ),
        Effect(
            "backlash",
            "steering backlash: the angle does not move until the command leaves a play band",
            {"width_deg": Param(6.0, "deg", "full width of the play", **_NONNEG)},
            "width_deg",
        ),
        Effect(
            "deadzone",
            "steering dead zone: commands within +-width give no angle, larger ones lose width",
            {"width_deg": Param(5.0, "deg", "half width of the dead zone", **_NONNEG)},
            "width_deg",
        ),
        Effect(
            "steer_limit",
            "steering end stops, possibly asymmetric: the wheel angle saturates",
            {
                "pos_deg": Param(45.0, "deg", "largest angle toward black (positive commands)", **_NONNEG),
                "neg_deg": Param(
                    45.0, "deg", "largest angle toward white (negative commands), as a magnitude", **_NONNEG
                ),
            },
            "pos_deg",
        ),
        Effect(
            "noise",
            "Gaussian sensor noise on the colour reading",
            {"sigma": Param(1.5, "colour units", "standard deviation", **_NONNEG)},
            "sigma",
        ),
        Effect(
            "quantise",
            "sensor quantisation: the reading is rounded to a multiple of step",
            {"step": Param(1.0, "colour units", "quantisation step", **_POS)},
            "step",
        ),
        Effect(
            "lowpass",
            "sensor low-pass response: the reading follows the surface as a first-order system",
            {"tau_ms": Param(40.0, "ms", "time constant", **_POS)},
            "tau_ms",
        ),
        Effect(
            "saturation",
            "the sensor clips readings to its range",
            {
                "low": Param(0.0, "colour units", "lowest reading", **_SCALE),
                "high": Param(100.0, "colour units", "highest reading", **_SCALE),
            },
            "high",
        ),
        Effect(
            "battery",
            "battery sag: speed falls linearly over the run",
            {"sag": Param(0.2, "fraction", "speed lost by the end of the run", **_FRACTION)},
            "sag",
        ),
        Effect(
            "run_variation",
            "run-to-run differences of speed, steering grip and white reflectance",
            {
                "speed_sd": Param(0.05, "fraction", "relative sd of speed", **_NONNEG),
                "grip_sd": Param(0.05, "fraction", "relative sd of steering grip", **_NONNEG),
                "white_sd": Param(0.0, "colour units", "sd of the white reflectance", **_NONNEG),
            },
            "speed_sd",
        ),
        Effect(
            "patches",
            "slippery patches along the track reduce the steering grip",
            {
                "per_m": Param(2.0, "1/m", "patches per metre travelled", 0.0, 1000.0),
                "length_mm": Param(100.0, "mm", "patch length", **_NONNEG),
                "grip": Param(0.5, "fraction", "steering grip on a patch", **_FRACTION),
            },
            "per_m",
        ),
        Effect(
            "curvature",
            "curved lane: the edge turns under the robot",
            {
                "mean_per_m": Param(0.0, "1/m", "mean curvature"),
                "amp_per_m": Param(2.0, "1/m", "amplitude of the sinusoidal curvature"),
                "wavelength_m": Param(1.0, "m", "wavelength of the curvature", **_POS),
            },
            "amp_per_m",
        ),
        Effect(
            "jitter",
            "sampling jitter and rare long pauses (the robot stands still during a pause)",
            {
                "extra_ms": Param(
                    2.0, "ms", "mean of the exponential extra delay per period (floored to ms)", **_DURATION
                ),
                "pause_prob": Param(0.0, "1/tick", "probability of a long pause per period", **_FRACTION),
                "pause_ms": Param(11000.0, "ms", "mean pause length (uniform within +-25%)", **_DURATION),
            },
            "extra_ms",
        ),
        Effect(
            "glitch",
            "rare sensor glitches: a reading replaced by a uniform random value in 0..100",
            {"prob": Param(0.01, "1/sample", "glitch probability per sample", **_FRACTION)},
            "prob",
        ),
    )
}


def effect_params(
    name: str, value: Mapping[str, Any] | float | int | bool | None, registry: Mapping[str, Effect] | None = None
) -> dict[str, float] | None:
    """Full parameters of one effect from a user value; ``None``/``False``/``0`` switches it off.

    A bare number sets the primary parameter; a dict overrides any parameters; unknown names fail
    loudly, because a typo would otherwise silently generate logs without the intended effect. Every
    parameter must be a finite number within its range (:class:`Param`); the ValueError names the
    effect, the parameter and the value. ``registry`` is the effects known (default :data:`EFFECTS`).
    """
    registry = EFFECTS if registry is None else registry
    if name not in registry:
        raise ValueError(f"unknown twin effect {name!r}; known: {', '.join(registry)}")
    eff = registry[name]
    if value is None or value is False:
        return None
    if isinstance(value, Mapping):
        unknown = set(value) - set(eff.params)
        if unknown:
            raise ValueError(
                f"effect {name!r}: unknown parameter(s) {', '.join(sorted(map(str, unknown)))}; "
                f"known: {', '.join(eff.params)}"
            )
        out = {k: _number(name, k, value.get(k, p.default)) for k, p in eff.params.items()}
    elif value is True:
        out = {k: float(p.default) for k, p in eff.params.items()}
    else:
        v = _number(name, eff.primary, value)
        if v == 0 and name != "saturation":
            return None
        out = {k: float(p.default) for k, p in eff.params.items()}
        out[eff.primary] = v
    for k, p in eff.params.items():
        v = out[k]
        inside = (v > p.low if p.above else v >= p.low) and v <= p.high and (not p.whole or v == int(v))
        if not inside:
            raise ValueError(f"effect {name!r}: {k} must be {p.rule()} [{p.unit}], got {v:g}")
    if name == "saturation" and not out["low"] < out["high"]:
        raise ValueError(f"effect 'saturation': low must be below high, got {out['low']:g} and {out['high']:g}")
    return out


def _number(name: str, param: str, value: Any) -> float:
    """``value`` as a finite float, or a ValueError naming the effect, the parameter and the value."""
    try:
        if isinstance(value, (bool, Mapping, list, tuple)):
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"effect {name!r}: {param} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"effect {name!r}: {param} must be a finite number, got {v}")
    return v


def resolve(base: Mapping[str, Any], overrides: Mapping[str, Any] | None) -> dict[str, dict[str, float]]:
    """The active effects: a profile's effects with the caller's on top (``None``/0 turns one off)."""
    merged: dict[str, Any] = dict(base)
    merged.update(overrides or {})
    out = {}
    for name, value in merged.items():
        params = effect_params(name, value)
        if params is not None:
            out[name] = params
    return dict(sorted(out.items()))


def parse_effects(text: str | None, registry: Mapping[str, Effect] | None = None) -> dict[str, Any]:
    """``"delay=2,noise=1.5,jitter.pause_prob=0.01,glitch"`` -> effects dict for :func:`resolve`; each
    effect checked against ``registry`` (default :data:`EFFECTS`) with the user's spelling in the message."""
    registry = EFFECTS if registry is None else registry
    out: dict[str, Any] = {}
    said: set[str] = set()
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        key, sep, value = item.partition("=")
        name, dot, param = key.strip().partition(".")
        if name not in registry:
            raise ValueError(f"unknown twin effect {name!r}; known: {', '.join(registry)}")
        which = f"{name}.{param or registry[name].primary}" if sep else name
        if which in said:  # 'delay=2,delay=3' once kept 3 without a word
            raise ValueError(f"effect {name!r}: {key.strip()} is given twice")
        said.add(which)
        if dot:
            if param not in registry[name].params:
                known = ", ".join(registry[name].params)
                raise ValueError(f"effect {name!r}: unknown parameter {param!r}; known: {known}")
            if not sep:
                raise ValueError(f"effect {name!r}: {param} needs a value ({key.strip()}=...)")
            entry = out.get(name)
            entry = dict(entry) if isinstance(entry, dict) else {}
            entry[param] = _number(name, param, value.strip())
            out[name] = entry
        else:
            out[name] = _number(name, registry[name].primary, value.strip()) if sep else True
        effect_params(name, out[name], registry)  # validate now, with the user's spelling in the message
    return out


def describe() -> str:
    """Human-readable table of all effects for ``envi twin effects``."""
    lines = []
    for e in EFFECTS.values():
        lines.append(f"{e.name}: {e.description}")
        for k, p in e.params.items():
            star = " (primary)" if k == e.primary else ""
            lines.append(f"    {k} [{p.unit}] default {p.default:g}{star}: {p.doc}")
    return "\n".join(lines)


def steering_command(batch: Any, command: np.ndarray) -> np.ndarray:
    """The steering command after the actuator-side effects, in order: delay (``batch.queue``, a list
    of pending commands), dead zone, backlash (``batch.play``, updated) and end stops. Shared by both
    twin world families, whose steering paths differ only after this point."""
    fx = batch.fx
    if batch.queue:
        batch.queue.append(command)
        command = batch.queue.pop(0)
    if "deadzone" in fx:
        w = fx["deadzone"]["width_deg"]
        command = np.sign(command) * np.maximum(np.abs(command) - w, 0.0)
    if "backlash" in fx:
        half = fx["backlash"]["width_deg"] / 2
        batch.play = np.clip(batch.play, command - half, command + half)
        command = batch.play
    if "steer_limit" in fx:
        command = np.clip(command, -fx["steer_limit"]["neg_deg"], fx["steer_limit"]["pos_deg"])
    return command


def colour_reading(batch: Any, sensed: np.ndarray, resolution: float | None) -> np.ndarray:
    """The colour readings (N,) from the surface the sensor saw, after the sensor-side effects, in order:
    noise, glitches (a uniform 0..100 reading), saturation within the 0..100 scale, quantisation to its
    step (else to ``resolution``; None leaves the value unrounded). Shared by both twin world families."""
    fx, c = batch.fx, sensed.copy()
    if "noise" in fx:
        c = c + fx["noise"]["sigma"] * batch.rng.standard_normal(batch.n)
    if "glitch" in fx:
        hit = batch.rng.random(batch.n) < fx["glitch"]["prob"]
        c = np.where(hit, batch.rng.uniform(0, 100, batch.n), c)
    low, high = (fx["saturation"]["low"], fx["saturation"]["high"]) if "saturation" in fx else (0.0, 100.0)
    c = np.clip(c, max(low, 0.0), min(high, 100.0))
    step = fx["quantise"]["step"] if "quantise" in fx else resolution
    return c if step is None else np.round(c / step) * step

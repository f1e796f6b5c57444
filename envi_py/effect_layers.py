"""Effect layers: small parametric physical effects around a learnt model, and their run memory.

A model learnt from a clean robot cannot show an effect its logs do not hold (an actuator that
lags, a noisy sensor). A layer adds one, with one or two physical parameters, so the model can be
simulated "as if" the robot had it: the diagnosis fits a layer on the logs that show a gap
(:mod:`envi_py.diagnose.layers`), and the fitted layer then travels with the model into every
simulation, the export and the native engine (metadata ``envi.layers``; ``cpp/src/engine.cpp`` is
the C++ twin of :class:`LayerStack`, tested against it).

Action layers change what the model sees of the controller's commands (the log keeps the commands
themselves): ``delay`` (k ticks), ``lag`` (first order, tau in rows), ``play`` (backlash of a full
width), ``gain_drift`` (gain changing linearly over the run) and ``run_gain`` (a gain per run, its
sd). State layers change what the controller and the log see of the model's predicted states (the
model keeps its own prediction): ``noise`` (Gaussian sd), ``quantise`` (step) and ``saturation``
(clipping limits). Several layers apply in the order given.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .files import parse_json, read_text

ACTION_LAYERS = ("delay", "lag", "play", "gain_drift", "run_gain")
STATE_LAYERS = ("noise", "quantise", "saturation")
#: the layers that draw at random: two runs from one window differ under them
RANDOM_LAYERS = ("noise", "run_gain")
LAYERS = ACTION_LAYERS + STATE_LAYERS
#: the longest delay a layer may hold (its run memory is that many commands per run)
MAX_DELAY = 1000
#: the slowest lag, in rows: 1000 (40 s at 25 Hz) outlasts any run, and beyond about 1e16 rows the
#: filter's step rounds to nothing, so the commands would freeze without a word
MAX_LAG = 1000.0
#: the most layers a model may carry (the native engine keys each layer's draws by its index)
MAX_LAYERS = 64
#: the largest gain drift or per-run gain sd, as a fraction (1000 %): a drift of -1e308 once turned
#: every command into NaN, which the native engine wrote into the logs, exit 0
MAX_GAIN = 10.0

UNITS = {
    "delay": "ticks",
    "lag": "rows",
    "play": "action units",
    "gain_drift": "fraction",
    "run_gain": "fraction",
    "noise": "state units",
    "quantise": "state units",
    "saturation": "state units",
}


@dataclass(frozen=True)
class Layer:
    """One effect layer: its kind and parameters (``value``; ``low``/``high`` for saturation)."""

    kind: str
    value: float = 0.0
    low: float = -math.inf
    high: float = math.inf

    def __post_init__(self) -> None:
        if self.kind not in LAYERS:
            raise ValueError(f"unknown effect layer {self.kind!r}; known: {', '.join(LAYERS)}")
        if not math.isfinite(self.value) or self.value < 0 and self.kind != "gain_drift":
            raise ValueError(f"effect layer {self.kind}: parameter must be finite and not negative, got {self.value}")
        if self.kind == "delay" and (self.value != int(self.value) or self.value > MAX_DELAY):
            raise ValueError(f"effect layer delay: a whole number of ticks up to {MAX_DELAY}, got {self.value}")
        if self.kind == "lag" and self.value > MAX_LAG:
            raise ValueError(f"effect layer lag: a time constant up to {MAX_LAG:g} rows, got {self.value}")
        if self.kind in ("gain_drift", "run_gain") and abs(self.value) > MAX_GAIN:
            raise ValueError(f"effect layer {self.kind}: a fraction of at most {MAX_GAIN:g} in size, got {self.value}")
        if math.isnan(self.low) or math.isnan(self.high) or self.low > self.high:
            raise ValueError(f"effect layer {self.kind}: limits must be ordered numbers, got [{self.low}, {self.high}]")

    @property
    def identity(self) -> bool:
        """Does the layer change nothing (the fitting grid's 'no effect' point)?"""
        if self.kind == "saturation":
            return self.low == -math.inf and self.high == math.inf
        return self.value == 0

    def to_json(self) -> dict[str, Any]:
        """Plain JSON (an open clipping limit is null)."""
        return {k: (None if isinstance(v, float) and math.isinf(v) else v) for k, v in asdict(self).items()}

    @staticmethod
    def from_json(d: dict[str, Any]) -> Layer:
        """The layer of :meth:`to_json`; a wrong type or value is a ValueError."""
        if not isinstance(d, dict) or not isinstance(d.get("kind"), str):
            raise ValueError(f"an effect layer is an object with a 'kind', got {d!r}")
        numbers = {k: d.get(k) for k in ("value", "low", "high")}
        if any(v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))) for v in numbers.values()):
            raise ValueError(f"effect layer {d['kind']}: value, low and high must be numbers or null, got {d!r}")
        return Layer(
            d["kind"],
            float(numbers["value"] or 0.0),
            -math.inf if numbers["low"] is None else float(numbers["low"]),
            math.inf if numbers["high"] is None else float(numbers["high"]),
        )

    def text(self) -> str:
        if self.kind == "saturation":
            return f"saturation [{self.low:g}, {self.high:g}]"
        return f"{self.kind} {self.value:g} {UNITS[self.kind]}"


def read_layers(path: str | Path) -> tuple[Layer, ...]:
    """The layers of a layers file (``{"layers": [{"layer": {...}, ...}, ...]}``, as ``envi diagnose``
    writes it); anything else is one ValueError naming the file."""
    data = parse_json(read_text(path, "a layers file"), str(path), "a layers file")
    try:
        if len(data["layers"]) > MAX_LAYERS:
            raise ValueError(f"{len(data['layers'])} layers, at most {MAX_LAYERS}")
        return tuple(Layer.from_json(entry["layer"]) for entry in data["layers"])
    except KeyError as exc:
        raise ValueError(f"{path}: not a layers file (no key {exc})") from None
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{path}: not a layers file ({exc})") from None


def layers_json(layers: Sequence[Layer]) -> list[dict[str, Any]]:
    """The layers as plain JSON, in order: what the export's ``envi.layers``, a simulated log's
    provenance and a check report's provenance record."""
    return [layer.to_json() for layer in layers]


def describe(layers: Sequence[Layer]) -> str:
    """One phrase for a report or a provenance: 'delay 2 ticks, noise 1.5 state units'."""
    return ", ".join(layer.text() for layer in layers) or "none"


class _ActionMemory:
    """One action layer's per-run memory over a rollout."""

    def __init__(self, layer: Layer, window_actions: np.ndarray, steps: int, rng: np.random.Generator) -> None:
        self.layer, self.steps, self.t = layer, max(steps, 1), 0
        self.history = [a for a in np.moveaxis(window_actions, 1, 0)]  # commands so far, each (B, |a|)
        self.state = window_actions[:, -1].copy()
        self.gain = 1 + (
            layer.value * rng.standard_normal((window_actions.shape[0], 1)) if layer.kind == "run_gain" else 0
        )

    def __call__(self, command: np.ndarray) -> np.ndarray:
        kind, v = self.layer.kind, self.layer.value
        self.history.append(command)
        self.t += 1
        if kind == "delay":
            k = int(v)
            return self.history[-1 - k] if k < len(self.history) else self.history[0]
        if kind == "lag":
            a = 1.0 if v <= 0 else 1 - math.exp(-1 / v)
            self.state = self.state + (command - self.state) * a
            return self.state
        if kind == "play":
            self.state = np.clip(self.state, command - v / 2, command + v / 2)
            return self.state
        if kind == "gain_drift":
            return command * (1 + v * self.t / self.steps)
        return command * self.gain


class LayerStack:
    """The layers of one batched rollout with their run memory: what the controller and the log see
    of the model's states (:meth:`states`) and what the model sees of the commands (:meth:`commands`).

    ``window_actions`` (B, l, |a|) are sigma_0's commands (a delay's first outputs, a lag's and a
    play's starting position); ``rng`` draws the noise and the per-run gains, in layer order."""

    def __init__(
        self, layers: Sequence[Layer], window_actions: np.ndarray, steps: int, rng: np.random.Generator
    ) -> None:
        self.rng = rng
        self.state_layers = [layer for layer in layers if layer.kind in STATE_LAYERS]
        self.action_memory = [
            _ActionMemory(layer, window_actions, steps, rng) for layer in layers if layer.kind in ACTION_LAYERS
        ]

    def states(self, s: np.ndarray) -> np.ndarray:
        """What the controller and the log see of the predicted states ``s`` (B, |s|). An overflow is
        left to :func:`envi_py.simulate.sensor_reading`, which names it, without numpy's warning line."""
        with np.errstate(over="ignore", invalid="ignore"):
            return self._states(s)

    def _states(self, s: np.ndarray) -> np.ndarray:
        for layer in self.state_layers:
            if layer.kind == "noise":
                s = s + layer.value * self.rng.standard_normal(s.shape)
            elif layer.kind == "quantise":
                s = np.round(s / layer.value) * layer.value if layer.value > 0 else s
            else:
                s = np.clip(s, layer.low, layer.high)
        return s

    def commands(self, command: np.ndarray) -> np.ndarray:
        """What the model sees of this step's commands (B, |a|)."""
        for memory in self.action_memory:
            command = memory(command)
        return command


def layered_commands(layers: Sequence[Layer], actions: np.ndarray) -> np.ndarray:
    """What the model sees of one log's commands (T, |a|) through action layers (the first row is
    sigma_0's last command, kept as is)."""
    stack = LayerStack(layers, actions[None, :1], len(actions), np.random.default_rng(0))
    return np.concatenate([actions[:1], *[stack.commands(a[None])[:1] for a in actions[1:]]])

"""Controllers under verification, declared once as ``{"name": ..., "params": {...}}``.

The same declarative spec drives the Python controllers here, the C++ runtime and the brick
program, so a controller is written down in one place and the other forms are tested against it.
Controllers are batched: they map states of N simulations at once, shape (N, |s|), to actions
(N, |a|), and may keep per-simulation memory (a PID's integral) between ``reset`` calls.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np


class Controller(Protocol):
    """What the simulator needs from a controller."""

    def reset(self, n: int) -> None: ...

    def __call__(self, states: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ControllerSpec:
    """A controller by name and parameters; the single source of truth for every runtime."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "params": dict(self.params)}

    @staticmethod
    def from_json(d: dict[str, Any]) -> "ControllerSpec":
        return ControllerSpec(str(d["name"]), dict(d.get("params", {})))

    def build(self) -> Controller:
        return make_controller(self)

    def __hash__(self) -> int:  # params is a dict; hash its sorted items
        return hash((self.name, tuple(sorted((k, str(v)) for k, v in self.params.items()))))


class LaneKeeping:
    """Paper, Algorithm 1: steer +x when brighter than the threshold, -x when darker, 0 on it.

    The threshold is 40 for the real robot (midpoint of black 5 and white 75); the paper's text
    says 50 (gray), but the logs satisfy ``angle == sign(color - 40) * x`` on every row.
    """

    defaults = {"x": 30.0, "threshold": 40.0}

    def __init__(self, x: float = 30.0, threshold: float = 40.0) -> None:
        self.x = float(x)
        self.threshold = float(threshold)

    def reset(self, n: int) -> None:
        """Stateless: nothing to reset."""

    def __call__(self, states: np.ndarray) -> np.ndarray:
        return np.sign(states[:, :1] - self.threshold) * self.x


class PID:
    """Discrete PID on the first state channel toward ``setpoint``, output clamped to limits.

    Uses the backward-Euler integral with anti-windup by clamping (the integral stops growing while
    the output saturates), the usual choice on small embedded controllers.
    """

    defaults = {"kp": 1.0, "ki": 0.0, "kd": 0.0, "setpoint": 40.0, "dt": 0.04,
                "out_min": -90.0, "out_max": 90.0}

    def __init__(self, kp: float = 1.0, ki: float = 0.0, kd: float = 0.0, setpoint: float = 40.0,
                 dt: float = 0.04, out_min: float = -90.0, out_max: float = 90.0) -> None:
        if out_min > out_max:
            raise ValueError(f"pid: out_min {out_min} > out_max {out_max}")
        if dt <= 0:
            raise ValueError(f"pid: dt must be positive, got {dt}")
        self.kp, self.ki, self.kd = float(kp), float(ki), float(kd)
        self.setpoint, self.dt = float(setpoint), float(dt)
        self.out_min, self.out_max = float(out_min), float(out_max)
        self.reset(0)

    def reset(self, n: int) -> None:
        self._integral = np.zeros((n, 1))
        self._prev: np.ndarray | None = None

    def __call__(self, states: np.ndarray) -> np.ndarray:
        err = states[:, :1] - self.setpoint
        if self._integral.shape[0] != err.shape[0]:
            self.reset(err.shape[0])
        deriv = np.zeros_like(err) if self._prev is None else (err - self._prev) / self.dt
        self._prev = err.copy()
        integral = self._integral + err * self.dt
        raw = self.kp * err + self.ki * integral + self.kd * deriv
        out = np.clip(raw, self.out_min, self.out_max)
        unsaturated = out == raw
        self._integral = np.where(unsaturated, integral, self._integral)
        return out


class FunctionController:
    """Adapter for a user's plain function ``f(states, **params) -> actions`` (stateless)."""

    def __init__(self, fn: Callable[..., np.ndarray], params: dict[str, Any]) -> None:
        self.fn, self.params = fn, params

    def reset(self, n: int) -> None:
        """Plain functions carry no memory."""

    def __call__(self, states: np.ndarray) -> np.ndarray:
        out = np.asarray(self.fn(states, **self.params), dtype=np.float64)
        return out.reshape(states.shape[0], -1)


REGISTRY: dict[str, type] = {"lane-keeping": LaneKeeping, "pid": PID}


def _import(path: str) -> Any:
    module, _, attr = path.partition(":")
    if not module or not attr:
        raise ValueError(f"controller {path!r}: expected 'package.module:function'")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"controller {path!r}: cannot import ({exc})") from exc


def make_controller(spec: ControllerSpec) -> Controller:
    """Instantiate a registered controller, or a user's by import path ``package.module:name``."""
    if spec.name in REGISTRY:
        cls = REGISTRY[spec.name]
        unknown = set(spec.params) - set(cls.defaults)
        if unknown:
            raise ValueError(f"controller {spec.name!r}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                             f"known: {', '.join(cls.defaults)}")
        return cls(**{k: float(v) for k, v in spec.params.items()})
    if ":" in spec.name:
        obj = _import(spec.name)
        if inspect.isclass(obj):
            return obj(**spec.params)
        if callable(obj):
            return FunctionController(obj, spec.params)
        raise ValueError(f"controller {spec.name!r}: not callable")
    raise ValueError(f"unknown controller {spec.name!r}; registered: {', '.join(REGISTRY)}, "
                     "or give 'package.module:function'")


def parse_params(items: list[str] | None) -> dict[str, Any]:
    """``["x=30", "threshold=40"]`` -> ``{"x": 30.0, "threshold": 40.0}`` (numbers where possible)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"parameter {item!r}: expected name=value")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            out[key.strip()] = value
    return out

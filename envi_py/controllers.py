"""Controllers under verification, declared once as ``{"name": ..., "params": {...}}``.

The same declarative spec drives the Python controllers here, the C++ runtime (``cpp/src/
controller.cpp``, checked against these by ``tests/test_controller_parity.py``) and the brick
program, so a controller is written down in one place and the other forms are tested against it.

The protocol every controller follows (registered or a user's class):

- ``reset(n)``: forget all memory; ``n`` runs are about to be simulated side by side.
- ``warmup(states, actions)``: replay the initial window sigma_0, states (n, l, |s|) and the logged
  actions (n, l, |a|), so that memory (a PID's integral and previous error) matches the real
  controller's when simulation starts at row l. The default replays the states through
  ``__call__`` and discards the answers.
- ``__call__(states)``: states (n, |s|) -> actions (n, |a|). The width is checked: a controller that
  answers with another number of columns than the model has actions is an error naming it, never
  broadcast.

Built-ins: ``bang-bang`` (the paper's Algorithm 1 on any state channel; ``lane-keeping`` is the
paper's robot, threshold 40 on channel 0), ``pid`` (one loop: P, I, D, output limits, clamping
anti-windup, an output offset) and ``combine`` (one loop per action channel, in action order). A
user's controller is ``package.module:name``: a class following the protocol, or a plain function
``f(states, **params) -> actions`` (stateless).
"""

from __future__ import annotations

import importlib
import inspect
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # system.py reads this module's registry: the type only, not a cycle
    from .system import Channel


@runtime_checkable
class Controller(Protocol):
    """What the simulator needs from a controller (see the module docstring)."""

    def reset(self, n: int) -> None: ...

    def __call__(self, states: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class ControllerSpec:
    """A controller by name and parameters; the single source of truth for every runtime."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "params": json.loads(json.dumps(self.params))}

    @staticmethod
    def from_json(d: Any) -> "ControllerSpec":
        if not isinstance(d, dict) or not isinstance(d.get("name"), str):
            raise ValueError(f"controller spec must be an object with a 'name', not {d!r:.80}")
        params = d.get("params") or {}
        if not isinstance(params, dict):
            raise ValueError(f"controller {d['name']!r}: 'params' must be an object")
        return ControllerSpec(d["name"], dict(params))

    @property
    def key(self) -> str:
        """A stable text key (sorted JSON): logs of one controller version share it. Numbers are
        keyed by value, so that ``x=30`` from a command line and ``30.0`` from a log's file name or
        sidecar are one version (they were two, and a report showed x = 30 twice)."""
        return json.dumps(_by_value(self.to_json()), sort_keys=True)

    def label(self) -> str:
        """``name(k=v, ...)`` for tables; nested loops shown by their own labels."""
        return _label(self.name, self.params)

    def build(
        self, n_state: int | None = None, n_action: int | None = None, period_ms: float | None = None
    ) -> Controller:
        """A fresh controller. With ``n_state``/``n_action`` its widths are checked against the
        model's; ``period_ms`` is the control period a PID integrates over unless it sets ``dt``."""
        return make_controller(self, n_state, n_action, period_ms)

    def __hash__(self) -> int:
        return hash(self.key)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ControllerSpec) and self.key == other.key


def finite_numbers(node: Any, what: str) -> Any:
    """Every number in a JSON tree finite: a NaN or infinite controller gain is never a version."""
    stack = [node]
    while stack:
        item = stack.pop()
        if isinstance(item, float) and not math.isfinite(item):
            raise ValueError(f"{what} hold a non-finite number ({item})")
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
    return node


def _by_value(v: Any) -> Any:
    """A JSON tree with every integral float written as an int (booleans stay booleans)."""
    if isinstance(v, dict):
        return {k: _by_value(e) for k, e in v.items()}
    if isinstance(v, list):
        return [_by_value(e) for e in v]
    if isinstance(v, float) and v.is_integer():
        return int(v)
    return v


def _label(name: str, params: dict[str, Any]) -> str:
    parts = []
    for k, v in params.items():
        if isinstance(v, list) and all(isinstance(e, dict) and "name" in e for e in v):
            parts.append(f"{k}=[" + ", ".join(_label(e["name"], e.get("params", {})) for e in v) + "]")
        elif isinstance(v, float) and v.is_integer() and abs(v) < 1e15:  # 1e308 is not 309 digits
            parts.append(f"{k}={int(v)}")
        else:
            parts.append(f"{k}={v:g}" if isinstance(v, (int, float)) else f"{k}={v}")
    return f"{name}({', '.join(parts)})"


class WidthError(ValueError):
    """A controller whose inputs or outputs do not fit the model's states and actions."""


class ControllerError(ValueError):
    """A controller that failed while running: it raised, or answered NaN, inf or a value outside
    the actions' declared range (a simulated log holding it could not be read back)."""


def _channel(name: str, value: Any, n_state: int | None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or float(value) != int(value):
        raise ValueError(f"controller {name!r}: 'input' must be a state channel index, not {value!r:.40}")
    idx = int(value)
    if idx < 0 or (n_state is not None and idx >= n_state):
        raise WidthError(f"controller {name!r}: reads state channel {idx}, the model has {n_state} state(s)")
    return idx


class Loop:
    """One output channel computed from one state channel; the pieces ``combine`` assembles."""

    name = "loop"
    outputs = 1

    def __init__(self, input: int) -> None:
        self.input = input

    def reset(self, n: int) -> None:
        """Stateless by default."""

    def warmup(self, states: np.ndarray, actions: np.ndarray) -> None:
        """Replay sigma_0's states through the loop, discarding its answers."""
        for t in range(states.shape[1]):
            self(states[:, t])


class BangBang(Loop):
    """Paper, Algorithm 1: +x when the input is above the threshold, -x below it, 0 on it.

    For the lane-keeping robot the threshold is 40 (midpoint of black 5 and white 75); the paper's
    text says 50 (gray), but the real logs satisfy ``angle == sign(color - 40) * x`` on every row.
    """

    name = "bang-bang"
    defaults: dict[str, float] = {"x": 30.0, "threshold": 40.0, "input": 0}

    def __init__(self, x: float = 30.0, threshold: float = 40.0, input: int = 0) -> None:
        super().__init__(input)
        self.x, self.threshold = float(x), float(threshold)

    def __call__(self, states: np.ndarray) -> np.ndarray:
        return np.sign(states[:, self.input : self.input + 1] - self.threshold) * self.x


class PID(Loop):
    """Discrete PID toward ``setpoint`` on one state channel: ``offset + kp e + ki I + kd de/dt``
    with ``e = state - setpoint``, clamped to [out_min, out_max].

    Backward-Euler integral with anti-windup by clamping (the integral stops growing while the
    output saturates), the usual choice on small embedded controllers. ``dt`` in seconds; by
    default the control period of the logs. The first call after a reset has no previous error,
    so its derivative is 0: which is why the simulator warms a PID up on sigma_0 first.
    ``terms`` holds the last call's P, I and D contributions, (n, 3), as a brick logs them.
    """

    name = "pid"
    defaults: dict[str, float | None] = {
        "kp": 1.0,
        "ki": 0.0,
        "kd": 0.0,
        "setpoint": 40.0,
        "dt": None,
        "out_min": -90.0,
        "out_max": 90.0,
        "offset": 0.0,
        "input": 0,
    }

    def __init__(
        self,
        kp: float = 1.0,
        ki: float = 0.0,
        kd: float = 0.0,
        setpoint: float = 40.0,
        dt: float | None = None,
        out_min: float = -90.0,
        out_max: float = 90.0,
        offset: float = 0.0,
        input: int = 0,
        period_ms: float | None = None,
    ) -> None:
        super().__init__(input)
        if dt is None:
            dt = (period_ms or 40.0) / 1000.0
        if not float(out_min) <= float(out_max):
            raise ValueError(f"pid: out_min {out_min} > out_max {out_max}")
        if not float(dt) > 0:
            raise ValueError(f"pid: dt must be positive, got {dt}")
        self.kp, self.ki, self.kd = float(kp), float(ki), float(kd)
        self.setpoint, self.dt, self.offset = float(setpoint), float(dt), float(offset)
        self.out_min, self.out_max = float(out_min), float(out_max)
        self.reset(0)

    def reset(self, n: int) -> None:
        self._integral = np.zeros((n, 1))
        self._prev: np.ndarray | None = None
        self.terms = np.zeros((n, 3))

    def __call__(self, states: np.ndarray) -> np.ndarray:
        err = states[:, self.input : self.input + 1] - self.setpoint
        if self._integral.shape[0] != err.shape[0]:
            self.reset(err.shape[0])
        deriv = np.zeros_like(err) if self._prev is None else (err - self._prev) / self.dt
        self._prev = err.copy()
        integral = self._integral + err * self.dt
        raw = self.offset + self.kp * err + self.ki * integral + self.kd * deriv
        out = np.clip(raw, self.out_min, self.out_max)
        self._integral = np.where(out == raw, integral, self._integral)
        self.terms = np.concatenate([self.kp * err, self.ki * integral, self.kd * deriv], axis=1)
        return out


class Combine:
    """One loop per action channel, in action order: a two-loop vehicle is steering + speed."""

    def __init__(self, loops: list[Loop]) -> None:
        self.loops = loops
        self.outputs = len(loops)

    def reset(self, n: int) -> None:
        for lp in self.loops:
            lp.reset(n)

    def warmup(self, states: np.ndarray, actions: np.ndarray) -> None:
        for lp in self.loops:
            lp.warmup(states, actions)

    def __call__(self, states: np.ndarray) -> np.ndarray:
        return np.concatenate([lp(states) for lp in self.loops], axis=1)


class Checked:
    """A controller whose answers are checked for width and finiteness on every call."""

    def __init__(self, inner: Any, name: str, n_action: int | None) -> None:
        self.inner, self.name, self.n_action = inner, name, n_action

    def _raised(self, what: str, exc: BaseException) -> ControllerError:
        return ControllerError(f"controller {self.name!r} raised {type(exc).__name__} in {what}: {exc}")

    def reset(self, n: int) -> None:
        try:
            self.inner.reset(n)
        except (WidthError, ControllerError):
            raise
        # a user's controller: its failure is one error line, not a traceback; its sys.exit() too,
        # which would otherwise end the command with the controller's exit code and no word
        except (Exception, SystemExit) as exc:
            raise self._raised("reset", exc) from exc

    def warmup(self, states: np.ndarray, actions: np.ndarray) -> None:
        try:
            if hasattr(self.inner, "warmup"):
                self.inner.warmup(states, actions)
            else:
                for t in range(states.shape[1]):
                    self.inner(states[:, t])
        except (WidthError, ControllerError):
            raise
        except (Exception, SystemExit) as exc:
            raise self._raised("warmup", exc) from exc

    def __call__(self, states: np.ndarray) -> np.ndarray:
        try:
            out = np.asarray(self.inner(states), dtype=np.float64)
        except (WidthError, ControllerError):
            raise
        except (Exception, SystemExit) as exc:
            raise self._raised("a step", exc) from exc
        if out.ndim == 1 and out.shape[0] == states.shape[0]:
            out = out[:, None]
        if (
            out.ndim != 2
            or out.shape[0] != states.shape[0]
            or (self.n_action is not None and out.shape[1] != self.n_action)
        ):
            want = f"({states.shape[0]}, {self.n_action})" if self.n_action is not None else f"({states.shape[0]}, k)"
            raise WidthError(
                f"controller {self.name!r} answered shape {tuple(out.shape)} for {states.shape[0]} "
                f"run(s); the model needs {want}"
            )
        if not np.isfinite(out).all():
            bad = out[~np.isfinite(out)][0]
            raise ControllerError(f"controller {self.name!r} answered a non-finite action ({bad})")
        return out


class FunctionController:
    """Adapter for a user's plain function ``f(states, **params) -> actions`` (stateless)."""

    def __init__(self, fn: Callable[..., np.ndarray], params: dict[str, Any]) -> None:
        self.fn, self.params = fn, params

    def reset(self, n: int) -> None:
        """Plain functions carry no memory."""

    def __call__(self, states: np.ndarray) -> np.ndarray:
        return np.asarray(self.fn(states, **self.params), dtype=np.float64)


#: Registered loops by name; ``lane-keeping`` is the paper's bang-bang with its robot's defaults.
LOOPS: dict[str, type[Loop]] = {"bang-bang": BangBang, "lane-keeping": BangBang, "pid": PID}
#: Every registered controller name (the native runtime runs exactly these).
REGISTRY: tuple[str, ...] = (*LOOPS, "combine")


def _import(path: str) -> Any:
    module, _, attr = path.partition(":")
    if not module or not attr:
        raise ValueError(f"controller {path!r}: expected 'package.module:function'")
    try:
        return getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"controller {path!r}: cannot import ({exc})") from exc


def _number(name: str, key: str, value: Any) -> float | None:
    if value is None and key == "dt":
        return None  # the period the controller is built for
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"controller {name!r}: parameter {key!r} must be a number, not {value!r:.40}")
    try:
        return float(value)
    except (ValueError, OverflowError):  # OverflowError: an integer past a float's range
        raise ValueError(f"controller {name!r}: parameter {key!r} must be a number, not {str(value)[:40]!r}") from None


def _loop(spec: ControllerSpec, n_state: int | None, period_ms: float | None) -> Loop:
    cls = LOOPS.get(spec.name)
    if cls is None:
        raise ValueError(f"combine: loop {spec.name!r} is not one of {', '.join(LOOPS)}")
    unknown = set(spec.params) - set(cls.defaults)
    if unknown:
        raise ValueError(
            f"controller {spec.name!r}: unknown parameter(s) "  # a name holding a line break stays on the line
            f"{', '.join(n if n.isidentifier() else repr(n) for n in sorted(unknown))}; "
            f"known: {', '.join(cls.defaults)}"
        )
    kwargs: dict[str, Any] = {k: _number(spec.name, k, v) for k, v in spec.params.items() if k != "input"}
    kwargs["input"] = _channel(spec.name, spec.params.get("input", 0), n_state)
    if cls is PID:
        kwargs["period_ms"] = period_ms
    return cls(**kwargs)


def make_controller(
    spec: ControllerSpec, n_state: int | None = None, n_action: int | None = None, period_ms: float | None = None
) -> Controller:
    """Instantiate a registered controller, or a user's by import path ``package.module:name``."""
    if spec.name in LOOPS:
        inner: Any = _loop(spec, n_state, period_ms)
        outputs: int | None = 1
    elif spec.name == "combine":
        loops = spec.params.get("loops")
        if set(spec.params) != {"loops"} or not isinstance(loops, list) or not loops:
            raise ValueError("controller 'combine': params must be {'loops': [spec, ...]}, one loop per action")
        inner = Combine([_loop(ControllerSpec.from_json(lp), n_state, period_ms) for lp in loops])
        outputs = len(loops)
    elif ":" in spec.name:
        obj = _import(spec.name)
        if inspect.isclass(obj):
            inner = obj(**spec.params)
        elif callable(obj):
            inner = FunctionController(obj, spec.params)
        else:
            raise ValueError(f"controller {spec.name!r}: not callable")
        if not callable(getattr(inner, "reset", None)):
            raise ValueError(f"controller {spec.name!r}: has no reset(n) method (see envi_py.controllers)")
        outputs = None
    else:
        raise ValueError(
            f"unknown controller {spec.name!r}; registered: {', '.join(REGISTRY)}, or give 'package.module:function'"
        )
    if outputs is not None and n_action is not None and outputs != n_action:
        raise WidthError(
            f"controller {spec.label()!r} drives {outputs} action channel(s), the model has "
            f"{n_action}; use 'combine' with one loop per action"
        )
    return Checked(inner, spec.name, n_action)


def parse_params(items: list[str] | None, option: str = "parameter") -> dict[str, Any]:
    """``["x=30", "threshold=40"]`` -> ``{"x": 30.0, "threshold": 40.0}`` (numbers where possible).

    A non-finite number (``x=nan``, ``x=inf``) is a ValueError naming the parameter: a NaN gain runs
    and writes logs full of NaN. ``option`` names where the items came from (``--param``) in errors."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{option} {item!r}: expected name=value")
        if key.strip() in out:  # 'x=30 x=40' once kept x=40 without a word
            raise ValueError(f"{option} {item!r}: {key.strip()} is given twice")
        try:
            number = float(value)
        except ValueError:
            out[key.strip()] = value
            continue
        if not math.isfinite(number):
            raise ValueError(f"{option} {item!r}: {key.strip()} is non-finite ({number}); give a finite number")
        out[key.strip()] = number
    return out


def in_range(commands: np.ndarray, channels: Sequence["Channel"], controller: ControllerSpec) -> np.ndarray:
    """``commands`` (B, |a|) when every one lies in its action channel's declared range; else a
    ControllerError naming the controller, the channel and the value (a log holding it could not be
    read back, and no actuator of the described system can do it)."""
    for j, ch in enumerate(channels):
        col = commands[:, j]
        bad = (col < ch.low) | (col > ch.high)
        if bad.any():
            raise ControllerError(
                f"controller {controller.label()!r} commanded {ch.name} = {col[bad][0]:g}, outside its declared "
                f"range [{ch.low:g}, {ch.high:g}]"
            )
    return commands

"""The system description: one TOML file that says what a system's logs hold and what its goals are.

It travels with the data and is recorded in every checkpoint, export, manifest and report, so a
model can always say which signals it reads and writes. It declares

- ``[system]``: a name and the nominal control period;
- ``[[signals]]``: every logged column but ``time``, with its role (``state``: a sensor reading the
  model predicts; ``action``: what the controller commands; ``logged``: kept with the log but not
  modelled, e.g. a PID's internal terms; ``ignore``: dropped on read), unit, valid range, sensor
  resolution and whether the sensor saturates at its range (an out-of-range reading is then
  clipped there, else it is an error);
- ``[versions]``: how a log says which controller version produced it, from a file-name
  ``pattern`` (``log_{x}_{run}.csv``: fields become controller parameters, ``run`` the run id) or
  from sidecars; ``params`` names the version parameters, ``map`` routes a field into a nested
  controller parameter (``kp_steer = "loops.0.params.kp"``);
- ``[controller]``: the controller's registered name or import path and its fixed parameters;
- ``[[goals]]`` and ``[[requirements]]``: goal metrics over the signals, and requirements with the
  probability they must hold with (``envi_py.goals``); ``preset`` names a shipped set of goals;
- ``[training]``: the model settings measured best for this system, which ``envi train`` (and
  everything that trains: demo, experiment) uses unless told otherwise: ``residual`` (the mean head
  predicts the change from the last reading), ``input_noise`` (behaviour cloning's window
  perturbation, in typical logged steps), ``step_noise`` (a Gaussian head's draws: ``gaussian``,
  or ``student-t`` or ``two-scale`` with tails fitted after training), ``context`` (sigma_0's per-state mean and
  spread as an input all run long, so a run keeps what its start showed of it), ``members`` (a
  seed ensemble of that many trainings, each simulated run drawn by one of them), ``hidden`` (the
  network's widths) and ``select_runs`` (simulated runs per validation log when choosing the epoch).

The lane-keeping robot and the car following a lead vehicle are shipped descriptions
(``envi_py/systems/*.toml``); ``envi init --logs DIR`` drafts one from a folder of logs.
"""

from __future__ import annotations

import difflib
import json
import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from .controllers import LOOPS, REGISTRY, ControllerSpec, finite_numbers
from .files import parse_toml, read_text, regular_file

ROLES = ("state", "action", "logged", "ignore")
#: A column name a CSV header can hold as is: no separator, quote or line break, no surrounding spaces.
COLUMN_NAME = re.compile(r'^[^,"\r\n\x00\s](?:[^,"\r\n\x00]*[^,"\r\n\x00\s])?$')
SHIPPED_DIR = Path(__file__).resolve().parent / "systems"


@dataclass(frozen=True)
class Channel:
    """One logged quantity: its column name, unit, physically valid range and sensor resolution.

    ``saturates``: the sensor clips at its range (an ultrasonic sensor reads its maximum when
    nothing is in range), so a value beyond the range is clipped on read, not refused."""

    name: str
    unit: str = ""
    low: float = -math.inf
    high: float = math.inf
    resolution: float | None = None
    saturates: bool = False

    def reads(self, values: Any, level: Any) -> np.ndarray:
        """Where ``values`` are the reading ``level`` (a number, or readings of the same shape): within
        half the declared resolution step, else within 1e-6 of it (relative beyond 1). The one test of
        "the same reading", for the limit events, the event head's targets, the in-range clamp and a
        run that repeats itself (:mod:`envi_py.diagnose.cycles`) alike."""
        level = np.asarray(level, dtype=np.float64)
        tol = self.resolution / 2 if self.resolution else 1e-6 * np.maximum(1.0, np.abs(level))
        return np.abs(np.asarray(values, dtype=np.float64) - level) <= tol

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "unit": self.unit, "range": [self.low, self.high]}
        if self.resolution is not None:
            d["resolution"] = self.resolution
        if self.saturates:
            d["saturates"] = True
        return d

    @staticmethod
    def from_json(d: Any) -> "Channel":
        """Every field checked for its type: a string range, a list unit or ``saturates = "no"``
        would otherwise be read as something the user did not write."""
        if not isinstance(d, dict) or not isinstance(d.get("name"), str) or not d["name"]:
            raise ValueError(f"a channel must be an object with a 'name', not {d!r:.60}")
        name = d["name"]
        if not COLUMN_NAME.match(name):
            raise ValueError(
                f"channel name {name!r:.60} cannot be a CSV column (no separators, quotes, line "
                "breaks or surrounding spaces)"
            )
        rng = d.get("range", [-math.inf, math.inf])
        if not isinstance(rng, (list, tuple)) or len(rng) != 2:
            raise ValueError(f"channel {name!r}: 'range' must be [low, high]")
        if not all(_is_number(v) for v in rng):
            raise ValueError(f"channel {name!r}: 'range' must hold two numbers")
        low, high = float(rng[0]), float(rng[1])
        if math.isnan(low) or math.isnan(high) or not low < high:
            raise ValueError(f"channel {name!r}: range [{low:g}, {high:g}] is empty")
        res = d.get("resolution")
        if res is not None:
            if not _is_number(res) or not (res > 0 and math.isfinite(res)):
                raise ValueError(f"channel {name!r}: resolution must be a positive number")
            res = float(res)
        unit, saturates = d.get("unit", ""), d.get("saturates", False)
        if not isinstance(unit, str):
            raise ValueError(f"channel {name!r}: 'unit' must be a string")
        if not isinstance(saturates, bool):
            raise ValueError(f"channel {name!r}: 'saturates' must be true or false")
        return Channel(name, unit, low, high, res, saturates)


@dataclass(frozen=True)
class LogSchema:
    """Which columns are states, actions and logged-only. ``time`` (ms) always comes first; the
    model reads states and actions, ``logged`` columns travel with the log unmodelled."""

    states: tuple[Channel, ...]
    actions: tuple[Channel, ...]
    logged: tuple[Channel, ...] = ()

    @property
    def columns(self) -> list[str]:
        return ["time"] + [c.name for c in self.channels + self.logged]

    @property
    def channels(self) -> tuple[Channel, ...]:
        """The model's channels: states then actions."""
        return self.states + self.actions

    def state_index(self, name: str) -> int:
        for i, c in enumerate(self.states):
            if c.name == name:
                return i
        raise ValueError(f"no state signal {name!r}; states: {', '.join(c.name for c in self.states)}")

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "states": [c.to_json() for c in self.states],
            "actions": [c.to_json() for c in self.actions],
        }
        if self.logged:
            d["logged"] = [c.to_json() for c in self.logged]
        return d

    @staticmethod
    def from_json(d: Any) -> "LogSchema":
        if not isinstance(d, dict):
            raise ValueError("a schema must be an object with 'states' and 'actions'")
        parts = []
        for key in ("states", "actions", "logged"):
            items = d.get(key, [] if key == "logged" else None)
            if not isinstance(items, list) or (key != "logged" and not items):
                raise ValueError(f"schema '{key}' must be a non-empty list of channels")
            parts.append(tuple(Channel.from_json(c) for c in items))
        schema = LogSchema(*parts)
        names = schema.columns
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"schema names column(s) {', '.join(dup)} twice")
        return schema


@dataclass(frozen=True)
class Versions:
    """How a log says which controller version made it (see the module docstring)."""

    pattern: str | None = None
    params: tuple[str, ...] = ()
    map: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"pattern": self.pattern, "params": list(self.params), "map": dict(self.map)}


#: the shapes a Gaussian head's step noise may take (:mod:`envi_py.train.step_noise`)
STEP_NOISES = ("gaussian", "student-t", "two-scale")
#: BC's step-size schedules (:func:`envi_py.train.bc.learning_rate`)
LR_SCHEDULES = ("constant", "cosine")
#: most members a seed ensemble may have (each is a whole training)
MAX_MEMBERS = 32


#: the widest hidden layer a description or ``envi train --hidden`` may ask for
MAX_HIDDEN = 100_000
#: weights between consecutive layers at most (hidden ones here, the input layer too in ModelConfig):
#: 200 MB of float32, and as much again for Adam
MAX_HIDDEN_WEIGHTS = 50_000_000


def check_members(members: Any, what: str = "members") -> int:
    """A seed ensemble's size, refused (naming ``what``) unless a whole number in 1..MAX_MEMBERS."""
    if isinstance(members, bool) or not isinstance(members, int) or not 1 <= members <= MAX_MEMBERS:
        raise ValueError(f"{what} must be a whole number in 1..{MAX_MEMBERS}, not {members!r:.40}")
    return members


def check_hidden(hidden: Any, what: str = "hidden") -> tuple[int, ...]:
    """A network's hidden widths, refused (naming ``what``) unless a non-empty list of whole numbers
    in 1..MAX_HIDDEN: one check for the description's ``[training] hidden`` and ``--hidden``."""
    if (
        not isinstance(hidden, (list, tuple))
        or not hidden
        or any(isinstance(h, bool) or not isinstance(h, int) or not 1 <= h <= MAX_HIDDEN for h in hidden)
    ):
        raise ValueError(f"{what} must be a list of widths, each in 1..{MAX_HIDDEN}, not {hidden!r:.40}")
    weights = sum(a * b for a, b in zip(hidden[:-1], hidden[1:]))
    if weights > MAX_HIDDEN_WEIGHTS:  # 100000,100000 once asked for 40 GB at the first step
        raise ValueError(
            f"{what} {','.join(map(str, hidden))}: {weights:,} weights between hidden layers, "
            f"more than {MAX_HIDDEN_WEIGHTS:,} (the paper's 256,256 has 65,536)"
        )
    return tuple(hidden)


@dataclass(frozen=True)
class TrainingDefaults:
    """Model settings a system's description recommends (``[training]``): the defaults of a training
    on its logs, each overridden by the caller's own choice (``--residual`` / ``--no-residual``)."""

    residual: bool = False
    input_noise: float = 0.0
    step_noise: str = "gaussian"
    context: bool = False
    members: int = 1
    hidden: tuple[int, ...] | None = None  # the network's hidden widths; None: the trainer's (256, 256)
    #: simulated runs per validation log at each closed-loop validation; None: the trainer's (5)
    select_runs: int | None = None
    #: BC's step size over the epochs: "constant", or "cosine" (annealed to 0 over the epoch cap)
    lr_schedule: str = "constant"

    def for_algorithm(self, algorithm: str) -> dict[str, Any]:
        """The keyword arguments ``algorithm``'s trainer takes from these defaults: the residual head
        for every learnt model, input noise for behaviour cloning only (its loss, not GAIL's), and
        the ensemble's members and the hidden widths for behaviour cloning only (where they were
        measured)."""
        out: dict[str, Any] = {}
        if algorithm in ("bc", "gail", "bcxgail") and self.residual:
            out["residual"] = True
        if algorithm == "bc" and self.input_noise:
            out["input_noise"] = self.input_noise
        if algorithm in ("bc", "gail", "bcxgail") and self.step_noise != "gaussian":
            out["step_noise"] = self.step_noise
        if algorithm in ("bc", "gail", "bcxgail") and self.context:
            out["context"] = True
        if algorithm == "bc" and self.members > 1:  # measured for BC; a GAIL training is 3-30x longer
            out["members"] = self.members
        if algorithm == "bc" and self.hidden:
            out["hidden"] = self.hidden
        if algorithm == "bc" and self.lr_schedule != "constant":  # measured for BC; GAIL's PPO keeps its own
            out["lr_schedule"] = self.lr_schedule
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "residual": self.residual,
            "input_noise": self.input_noise,
            "step_noise": self.step_noise,
            "context": self.context,
            "members": self.members,
            "hidden": None if self.hidden is None else list(self.hidden),
            "select_runs": self.select_runs,
            "lr_schedule": self.lr_schedule,
        }


def _training(d: Any) -> TrainingDefaults:
    if d is None:
        return TrainingDefaults()
    if not isinstance(d, dict):
        raise ValueError("[training] must be a table")
    residual, context = d.get("residual", False), d.get("context", False)
    for key, value in (("residual", residual), ("context", context)):
        if not isinstance(value, bool):
            raise ValueError(f"[training] {key} must be true or false, not {value!r:.40}")
    noise = d.get("input_noise", 0.0)
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not 0 <= noise <= 100:  # NaN fails too
        raise ValueError(f"[training] input_noise must be a multiple of the typical step in 0..100, not {noise!r:.40}")
    step_noise = d.get("step_noise", "gaussian")
    if step_noise not in STEP_NOISES:
        raise ValueError(f"[training] step_noise must be one of {', '.join(STEP_NOISES)}, not {step_noise!r:.40}")
    members = check_members(d.get("members", 1), "[training] members")
    hidden = d.get("hidden")
    if hidden is not None:
        hidden = check_hidden(hidden, "[training] hidden")
    select_runs = d.get("select_runs")
    if select_runs is not None and (
        isinstance(select_runs, bool) or not isinstance(select_runs, int) or not 1 <= select_runs <= 1000
    ):
        raise ValueError(f"[training] select_runs must be a whole number in 1..1000, not {select_runs!r:.40}")
    schedule = d.get("lr_schedule", "constant")
    if schedule not in LR_SCHEDULES:
        raise ValueError(f"[training] lr_schedule must be one of {', '.join(LR_SCHEDULES)}, not {schedule!r:.40}")
    return TrainingDefaults(residual, float(noise), step_noise, context, members, hidden, select_runs, schedule)


@dataclass(frozen=True)
class GoalSpec:
    """A goal metric: a library metric (or ``package.module:function``) on one signal."""

    name: str
    metric: str
    signal: str
    params: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "metric": self.metric, "signal": self.signal, "params": dict(self.params)}


@dataclass(frozen=True)
class RequirementSpec:
    """A requirement: ``expr`` is a goal-metric comparison (``max_abs_dev(color, 40) <= 35``) or,
    with ``kind = "stl"``, a Signal Temporal Logic formula over the signals; it must hold with
    probability at least ``probability``."""

    name: str
    expr: str
    kind: str = "metric"
    probability: float = 0.9

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "expr": self.expr, "kind": self.kind, "probability": self.probability}


@dataclass(frozen=True)
class SystemDescription:
    """What a system's logs hold, how versions are told apart, its controller and its goals."""

    name: str
    schema: LogSchema
    period_ms: float | None = None
    versions: Versions = field(default_factory=Versions)
    controller: ControllerSpec | None = None
    ignore: tuple[str, ...] = ()
    preset: str | None = None
    goals: tuple[GoalSpec, ...] = ()
    requirements: tuple[RequirementSpec, ...] = ()
    training: TrainingDefaults = field(default_factory=TrainingDefaults)
    source: str | None = None  # the file it was read from, for messages

    # ------------------------------------------------------------------ versions of a log

    def check_version_fields(self, fields: dict[str, Any], what: str) -> None:
        """Refuse a field that is not one of the declared version parameters (``what`` names the
        option): set as it is, a misspelt gain became a controller parameter of that name, and the
        controller blamed its own structure instead."""
        unknown = sorted(set(fields) - set(self.versions.params))
        if self.versions.params and unknown:
            raise ValueError(
                f"{what}: system {self.name!r} has no version parameter {unknown[0]!r} "
                f"(its parameters: {', '.join(self.versions.params)})"
            )

    def controller_for(self, fields: dict[str, Any]) -> ControllerSpec | None:
        """The controller of a log whose file name gave ``fields`` (version parameters)."""
        if self.controller is None:
            return None
        params = json.loads(json.dumps(self.controller.params))
        for key, value in fields.items():
            _set_path(params, self.versions.map.get(key, key), value)
        return ControllerSpec(self.controller.name, params)

    def version_of(self, spec: ControllerSpec) -> dict[str, Any]:
        """The version parameters of a controller (``kp_steer`` read from ``loops.0.params.kp``);
        all its top-level parameters when the description names none."""
        if not self.versions.params:
            return dict(spec.params)
        out = {}
        for name in self.versions.params:
            node: Any = spec.params
            try:
                for k in self.versions.map.get(name, name).split("."):
                    node = node[int(k)] if isinstance(node, list) else node[k]
            except (KeyError, IndexError, ValueError, TypeError):
                continue
            out[name] = node
        return out

    def with_version_defaults(self, spec: ControllerSpec) -> ControllerSpec:
        """``spec`` with each top-level version parameter it leaves to a registered loop's default
        written out (``lane-keeping()`` becomes ``lane-keeping(x=30)``). Why: a log must say which
        version produced it, and a default the controller applies silently left twin logs that every
        command refused ("has no version parameter x")."""
        defaults = LOOPS[spec.name].defaults if spec.name in LOOPS else {}
        missing = {
            key: defaults[key]
            for key in (self.versions.map.get(p, p) for p in self.versions.params)
            if key not in spec.params and key in defaults
        }
        return ControllerSpec(spec.name, {**spec.params, **missing}) if missing else spec

    def version_params(self, spec: ControllerSpec) -> dict[str, Any]:
        """The version parameters of a controller in the description's order ({} when it names none).
        A controller lacking one of them is an error: its logs could not be told apart from others'."""
        if not self.versions.params:
            return {}
        found = self.version_of(spec)
        missing = [p for p in self.versions.params if p not in found]
        if missing:
            raise ValueError(
                f"controller {spec.label()} has no version parameter {', '.join(missing)} "
                f"(system {self.name!r} names {', '.join(self.versions.params)})"
            )
        return {p: found[p] for p in self.versions.params}

    def version_label(self, spec: ControllerSpec) -> str:
        """``x=30`` or ``kp_steer=0.8,kp_speed=18`` (numbers with ``:g``): how every table, report and
        command-line choice names a version; the controller's label when no version parameters are named."""
        params = self.version_params(spec)
        if not params:
            return spec.label()
        return ",".join(
            f"{k}={v:g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else f"{k}={v}"
            for k, v in params.items()
        )

    def with_pattern(self, pattern: str | None) -> "SystemDescription":
        """The same description reading version parameters from ``pattern`` (a command-line
        ``--pattern``); a different pattern declared in the file is a conflict, not overridden."""
        if pattern is None or pattern == self.versions.pattern:
            return self
        pattern_regex(pattern)  # a bad pattern (or not a string) is an error here, not a traceback later
        if self.versions.pattern is not None:
            raise ValueError(
                f"--pattern {pattern!r} contradicts the system description's pattern "
                f"{self.versions.pattern!r} ({self.source or self.name})"
            )
        fields = tuple(f for f in pattern_fields(pattern) if f != "run")
        return replace(self, versions=replace(self.versions, pattern=pattern, params=self.versions.params or fields))

    # ------------------------------------------------------------------ (de)serialisation

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "period_ms": self.period_ms,
            "schema": self.schema.to_json(),
            "ignore": list(self.ignore),
            "versions": self.versions.to_json(),
            "controller": None if self.controller is None else self.controller.to_json(),
            "preset": self.preset,
            "goals": [g.to_json() for g in self.goals],
            "requirements": [r.to_json() for r in self.requirements],
            "training": self.training.to_json(),
        }

    @staticmethod
    def from_json(d: Any, where: str = "system description") -> "SystemDescription":
        """From :meth:`to_json`'s form (as recorded in checkpoints, manifests and reports)."""
        if not isinstance(d, dict):
            raise ValueError(f"{where}: not an object")
        try:
            v = {} if d.get("versions") is None else d["versions"]
            if not isinstance(v, dict):
                raise ValueError("'versions' must be an object")
            desc = SystemDescription(
                name=_text(d.get("name", "system"), "name"),
                schema=LogSchema.from_json(d.get("schema")),
                period_ms=_period(d.get("period_ms")),
                versions=_versions(v.get("pattern"), v.get("params"), v.get("map")),
                controller=None if d.get("controller") is None else ControllerSpec.from_json(d["controller"]),
                ignore=tuple(_strings(d.get("ignore"), "ignore")),
                preset=_opt_text(d.get("preset"), "preset"),
                goals=tuple(_goal(g) for g in _list(d.get("goals"), "goals")),
                requirements=tuple(
                    _requirement(r, i) for i, r in enumerate(_list(d.get("requirements"), "requirements"))
                ),
                training=_training(d.get("training")),
                source=where,
            )
        except (AttributeError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        return _validated(desc, where)

    @staticmethod
    def from_toml_text(text: str, where: str) -> "SystemDescription":
        doc = parse_toml(text, where, "a system description")
        try:
            desc = _from_toml(doc, where)
        except (AttributeError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None
        return _validated(desc, where)

    @staticmethod
    def load(path: str | Path) -> "SystemDescription":
        return SystemDescription.from_toml_text(read_text(path, "a system description"), str(path))


def _is_number(v: Any) -> bool:
    """An int or float as written (``true`` and ``"40"`` are not numbers)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: A nominal period envi can take (ms): a checkpoint records it under the same bound.
PERIOD_RANGE_MS = (1e-3, 1e6)


def _period(v: Any) -> float | None:
    """The nominal period in ms, if given: 1 us to about 17 minutes (1e300 once passed)."""
    period = _opt_float(v, "period_ms")
    low, high = PERIOD_RANGE_MS
    if period is not None and not low <= period < high:
        raise ValueError(f"'period_ms' must lie in {low:g}..{high:g} ms, not {period:g}")
    return period


def _opt_float(v: Any, what: str) -> float | None:
    if v is None:
        return None
    if not _is_number(v) or not (math.isfinite(v) and v > 0):
        raise ValueError(f"'{what}' must be a positive number, not {v!r:.40}")
    return float(v)


def _text(v: Any, what: str) -> str:
    if not isinstance(v, str):
        raise ValueError(f"'{what}' must be a string, not {v!r:.40}")
    return v


def _opt_text(v: Any, what: str) -> str | None:
    return None if v is None else _text(v, what)


def _list(v: Any, what: str) -> list[Any]:
    """An optional list (absent: empty); a table or a number where a list belongs is an error."""
    if v is None:
        return []
    if not isinstance(v, list):
        raise ValueError(f"'{what}' must be a list, not {type(v).__name__}")
    return v


def _strings(v: Any, what: str) -> list[str]:
    items = _list(v, what)
    if not all(isinstance(s, str) and s for s in items):
        raise ValueError(f"'{what}' must be a list of names")
    return items


def _versions(pattern: Any, params: Any, mapping: Any) -> Versions:
    """``[versions]``: the pattern checked now (a bad one is this file's error), parameter names a
    list of strings (a string ``"xy"`` is not two names), ``map`` a table of strings."""
    if pattern is not None:
        pattern_regex(pattern)
    if params is None:
        params = [f for f in pattern_fields(pattern) if f != "run"] if pattern else []
    mapping = mapping or {}
    if not isinstance(mapping, dict) or not all(isinstance(m, str) and m for m in mapping.values()):
        raise ValueError("versions 'map' must be a table of parameter paths (strings)")
    return Versions(pattern, tuple(_strings(params, "versions params")), dict(mapping))


def _set_path(params: dict[str, Any], path: str, value: Any) -> None:
    """Set ``loops.0.kp`` in nested params (dicts and lists); a path through a number, a missing
    list index or a word where an index belongs is a ValueError naming the path."""
    keys = path.split(".")
    node: Any = params
    try:
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node.setdefault(k, {})
        if isinstance(node, list):
            node[int(keys[-1])] = value
        elif isinstance(node, dict):
            node[keys[-1]] = value
        else:
            raise TypeError
    except (AttributeError, IndexError, TypeError, ValueError):
        raise ValueError(f"version parameter path {path!r} does not lead into the controller's parameters") from None


def _goal(g: Any) -> GoalSpec:
    if not isinstance(g, dict):
        raise ValueError(f"a goal must be a table, not {g!r:.40}")
    for key in ("metric", "signal"):
        if not isinstance(g.get(key), str):
            raise ValueError(f"goal {g.get('name', '?')!r}: '{key}' must be a string")
    params = g["params"] if "params" in g else {k: v for k, v in g.items() if k not in ("name", "metric", "signal")}
    if not isinstance(params, dict):
        raise ValueError(f"goal {g.get('name', '?')!r}: 'params' must be a table")
    return GoalSpec(str(g.get("name") or f"{g['metric']}({g['signal']})"), g["metric"], g["signal"], dict(params))


def _requirement(r: Any, i: int) -> RequirementSpec:
    if isinstance(r, str):
        r = {"expr": r}
    if not isinstance(r, dict) or not isinstance(r.get("expr"), str):
        raise ValueError(f"requirement {i + 1}: needs an 'expr' string")
    kind = r.get("kind", "metric")
    if kind not in ("metric", "stl"):
        raise ValueError(f"requirement {i + 1}: kind must be 'metric' or 'stl', not {kind!r}")
    p = r.get("probability", 0.9)
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 < p < 1:
        raise ValueError(f"requirement {i + 1}: probability must lie strictly between 0 and 1")
    return RequirementSpec(str(r.get("name") or f"R{i + 1}"), r["expr"], kind, float(p))


#: The keys each part of a TOML description may hold: a typo ("periodms", "[sytem]") is an error
#: naming the key and the nearest known one, never a silently ignored setting.
TOML_KEYS: dict[str, tuple[str, ...]] = {
    "the top level": (
        "system",
        "signals",
        "versions",
        "controller",
        "goals",
        "requirements",
        "goals_preset",
        "training",
    ),
    "[system]": ("name", "period_ms", "goals_preset"),
    "[[signals]]": ("name", "role", "unit", "range", "resolution", "saturates"),
    "[versions]": ("pattern", "params", "map"),
    "[controller]": ("name", "params"),
    "[[requirements]]": ("name", "expr", "kind", "probability"),
    "[training]": (
        "residual",
        "input_noise",
        "step_noise",
        "context",
        "members",
        "hidden",
        "select_runs",
        "lr_schedule",
    ),
}


def _known_keys(table: Any, part: str) -> None:
    """Refuse a key ``part`` does not know, suggesting the nearest known one."""
    if not isinstance(table, dict):
        return
    known = TOML_KEYS[part]
    for key in table:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise ValueError(f"{part}: unknown key {key!r} ({hint}known: {', '.join(known)})")


def _from_toml(doc: dict[str, Any], where: str) -> SystemDescription:
    _known_keys(doc, "the top level")
    for part, key in (
        ("[system]", "system"),
        ("[versions]", "versions"),
        ("[controller]", "controller"),
        ("[training]", "training"),
    ):
        _known_keys(doc.get(key), part)
    for part, key in (("[[signals]]", "signals"), ("[[requirements]]", "requirements")):
        for entry in doc.get(key) if isinstance(doc.get(key), list) else ():
            _known_keys(entry, part)
    sysd = doc.get("system", {})
    if not isinstance(sysd, dict):
        raise ValueError("[system] must be a table")
    signals = doc.get("signals")
    if not isinstance(signals, list) or not signals:
        raise ValueError("no [[signals]] declared")
    groups: dict[str, list[Channel]] = {r: [] for r in ROLES}
    for s in signals:
        if not isinstance(s, dict):
            raise ValueError("each [[signals]] entry must be a table")
        role = s.get("role")
        if role not in ROLES:
            raise ValueError(f"signal {s.get('name', '?')!r}: role must be one of {', '.join(ROLES)}, not {role!r}")
        groups[role].append(Channel.from_json(s))
    schema = LogSchema(tuple(groups["state"]), tuple(groups["action"]), tuple(groups["logged"]))
    if not schema.states or not schema.actions:
        raise ValueError("at least one 'state' and one 'action' signal are needed")
    v = doc.get("versions", {})
    if not isinstance(v, dict):
        raise ValueError("[versions] must be a table")
    c = doc.get("controller")
    controller = None
    if c is not None:
        if not isinstance(c, dict):
            raise ValueError("[controller] must be a table")
        controller = ControllerSpec.from_json({"name": c.get("name"), "params": c.get("params", {})})
        # before the goals, which may read a parameter (the preset's centre is the threshold): a NaN
        # threshold was once blamed on goal 'steady_count'
        finite_numbers(controller.params, "[controller] params")
    return SystemDescription(
        name=_text(sysd.get("name", Path(where).stem), "name"),
        schema=schema,
        period_ms=_period(sysd.get("period_ms")),
        versions=_versions(v.get("pattern"), v.get("params"), v.get("map")),
        controller=controller,
        ignore=tuple(s["name"] for s in signals if s.get("role") == "ignore"),
        preset=_opt_text(doc.get("goals_preset") or sysd.get("goals_preset"), "goals_preset"),
        goals=tuple(_goal(g) for g in _list(doc.get("goals"), "goals")),
        requirements=tuple(_requirement(r, i) for i, r in enumerate(_list(doc.get("requirements"), "requirements"))),
        training=_training(doc.get("training")),
        source=where,
    )


def _validated(desc: SystemDescription, where: str) -> SystemDescription:
    names = desc.schema.columns + list(desc.ignore)
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{where}: signal(s) {', '.join(dup)} declared twice")
    if "time" in names[1:]:
        raise ValueError(f"{where}: a signal is named 'time', the name of every log's time column; name it otherwise")
    known = {c.name for c in desc.schema.states + desc.schema.actions + desc.schema.logged}
    for g in desc.goals:
        if g.signal not in known:
            raise ValueError(f"{where}: goal {g.name!r} reads signal {g.signal!r}, which is not declared")
    return desc


def _uses_checked(desc: SystemDescription, where: str) -> SystemDescription:
    """Every goal's metric and parameters and every requirement parse against the declared signals,
    and every version parameter's ``map`` path leads into the controller, so a typo in the file is
    refused (naming the file) when it is read, not after a training at ``envi check``."""
    from .goals.presets import goals_of  # lazily: the goals package reads this module's types
    from .goals.registry import KNOWN, metric
    from .goals.requirements import parse

    signals = [c.name for c in desc.schema.states + desc.schema.actions + desc.schema.logged]
    try:
        for g in goals_of(desc):
            m = metric(g.metric)
            if g.metric in KNOWN:  # a user's metric may take anything; envi's take numbers
                for k, v in g.params.items():
                    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                        raise ValueError(f"goal {g.name!r}: parameter {k!r} must be a finite number, not {v!r:.40}")
            unknown = sorted(set(g.params) - set(m.params))
            missing = [p for p in m.required if p not in g.params]
            if unknown or missing:
                raise ValueError(
                    f"goal {g.name!r}: metric {g.metric!r} "
                    + (f"has no parameter {unknown[0]!r}" if unknown else f"needs parameter {missing[0]!r}")
                    + f"; parameters: {', '.join(m.params) or 'none'}"
                )
        for r in desc.requirements:
            parse(r, signals)
        for what, names in (
            ("requirement", [r.name for r in desc.requirements]),  # each names one row of envi check's table
            ("version parameter", list(desc.versions.params)),
        ):
            twice = sorted({n for n in names if names.count(n) > 1})
            if twice:
                raise ValueError(f"{what} {twice[0]!r} is given twice; names must differ")
        if desc.controller is not None and desc.controller.name not in REGISTRY and ":" not in desc.controller.name:
            raise ValueError(
                f"unknown controller {desc.controller.name!r}; registered: {', '.join(REGISTRY)}, "
                "or give 'package.module:function'"
            )
        if desc.controller is not None:
            finite_numbers(desc.controller.params, f"[controller] {desc.controller.name!r}: params")
            if desc.controller.name in REGISTRY:  # its parameters' names, before any training reads them
                desc.controller.build(period_ms=desc.period_ms)
        if desc.controller is not None and desc.versions.map:
            mapped = desc.controller_for({p: 1 for p in desc.versions.map})
            if mapped is not None and mapped.name in REGISTRY:  # a path to a parameter the controller lacks
                mapped.build(period_ms=desc.period_ms)
    except ValueError as exc:
        msg = str(exc)
        raise ValueError(msg if msg.startswith(where) else f"{where}: {msg}") from None
    return desc


# ---------------------------------------------------------------------- file-name patterns


def pattern_fields(pattern: str) -> list[str]:
    return re.findall(r"\{(\w+)\}", pattern)


def pattern_regex(pattern: str) -> re.Pattern[str]:
    """``log_{x}_{run}.csv`` -> a regex with one named group per field (numbers or words).

    A field named twice, an empty name or a stray brace is an error naming the pattern."""
    if not isinstance(pattern, str) or not pattern:
        raise ValueError("a file-name pattern must be a non-empty string")
    fields = pattern_fields(pattern)
    odd = [f for f in fields if not f.isidentifier()]
    if odd:
        raise ValueError(
            f"pattern {pattern!r}: field {{{odd[0]}}} is not a name (letters, digits, '_'; not starting with a digit)"
        )
    dup = sorted({f for f in fields if fields.count(f) > 1})
    if dup:
        raise ValueError(f"pattern {pattern!r}: field {{{dup[0]}}} appears twice")
    if re.sub(r"\{\w+\}", "", pattern).count("{") or re.sub(r"\{\w+\}", "", pattern).count("}"):
        raise ValueError(f"pattern {pattern!r}: a brace that is not a {{field}}")
    touching = re.search(r"\{\w+\}\{\w+\}", pattern)
    if touching:  # 'log_{x}{run}.csv' once read log_30_1.csv as x=3, run '0_1'
        raise ValueError(
            f"pattern {pattern!r}: fields {touching.group(0)} touch; put a separator between them, "
            "as in log_{x}_{run}.csv"
        )
    out, pos = [], 0
    for m in re.finditer(r"\{(\w+)\}", pattern):
        out.append(re.escape(pattern[pos : m.start()]))
        out.append(f"(?P<{m.group(1)}>[-+\\w.]+?)")
        pos = m.end()
    out.append(re.escape(pattern[pos:]))
    return re.compile("^" + "".join(out) + "$")


# ---------------------------------------------------------------------- shipped descriptions


def shipped() -> dict[str, Path]:
    """Shipped descriptions by name (``lane-keeping``, ``car``)."""
    return {p.stem: p for p in sorted(SHIPPED_DIR.glob("*.toml"))}


def load_system(name_or_path: str | Path) -> SystemDescription:
    """A shipped description by name, or a TOML file (whose goals and requirements are parsed too: the
    shipped ones are by the tests, and at import time the goals package cannot be loaded yet)."""
    known = shipped()
    if str(name_or_path) in known:
        return SystemDescription.load(known[str(name_or_path)])
    path = Path(name_or_path)
    if not path.exists():
        raise ValueError(f"{path}: no such system description; shipped: {', '.join(known)}")
    regular_file(path, "a system description")
    return _uses_checked(SystemDescription.load(path), str(path))


def lane_keeping() -> SystemDescription:
    """The paper's LEGO lane-keeping robot: the default for logs with neither sidecar nor description."""
    return load_system("lane-keeping")


def describe_schema(schema: LogSchema) -> SystemDescription:
    """The description of logs that carry their own schema (twin, simulated, HIL sidecars): the
    shipped one with the same columns (so twin lane-keeping logs get the paper's goals), else a
    minimal one with no controller and no goals."""
    for path in shipped().values():
        known = SystemDescription.load(path)
        if known.schema.columns == schema.columns:
            return known
    return SystemDescription(name="from-sidecars", schema=schema)


def toml_value(v: Any) -> str:
    """One TOML value (numbers, strings, lists, inline tables) for drafts the user edits."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        if math.isnan(v):
            return "nan"
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(e) for e in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {toml_value(e)}" for k, e in v.items()) + "}"
    raise TypeError(f"no TOML form for {v!r}")


def names(channels: Iterable[Channel]) -> list[str]:
    return [c.name for c in channels]

"""Requirements on runs: a goal metric against a threshold, or a Signal Temporal Logic formula.

A *metric* requirement is one comparison of a goal metric of one signal with a number,
``max_abs_dev(color, 40) <= 35`` or ``min(distance) >= 10``: the metric's parameters follow the
signal positionally in the registry's order, or by keyword (``time_in_band(color, setpoint=40,
band=10) >= 0.8``). It is parsed with Python's :mod:`ast` (never evaluated), so anything but that
shape is refused with a message naming the requirement.

An *STL* requirement (``kind = "stl"``) is a discrete-time STL formula over the signals, checked by
``rtamt`` (a maintained STL monitor, rather than a hand-written one): ``always[0:100](color >= 5
and color <= 95)``, ``eventually[0:50](distance <= 40)``. A run satisfies it when its robustness
at time 0 is >= 0 (so a strict ``>`` holds on its boundary, as robustness cannot tell ``>`` from
``>=``).

Time: time 0 is the first *scored* sample (after the ``skip`` rows a simulation copies from its
real log), and rtamt is given the sample index as time with its default unit sampling period, so
**temporal bounds count samples** (control periods): at 40 ms, ``always[0:25]`` spans one second.
Bounds with a unit (``[0:1s]``) are refused, because rtamt would silently read them against its
own default unit rather than the control period. A bound beyond the end of the run is cut at the
run's end (rtamt's offline semantics: ``always`` over an empty stretch holds, ``eventually`` fails).

Speed: rtamt's offline monitor costs 1-2 ms per run of 100 samples (10,000 runs: 10-20 s per
requirement), so the common forms (a single ``always``/``eventually`` with an optional bound over a
Boolean combination of comparisons of arithmetic on signals, or such a combination alone) are
computed directly with numpy over all runs at once; rtamt still parses every formula (its syntax
errors are the user's messages) and checks every other form. Tests hold the two equal.
"""

from __future__ import annotations

import ast
import logging
import math
import operator
import re
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import rtamt
from rtamt.exception.exception import RTAMTException

from ..system import RequirementSpec
from .evaluate import Runs
from .registry import KNOWN, metric

COMPARISONS: dict[type, tuple[str, Callable[[Any, Any], Any]]] = {
    ast.Lt: ("<", operator.lt),
    ast.LtE: ("<=", operator.le),
    ast.Gt: (">", operator.gt),
    ast.GtE: (">=", operator.ge),
}
FLIPPED = {"<": ">", "<=": ">=", ">": "<", ">=": "<="}
OPS = {sym: fn for sym, fn in COMPARISONS.values()}


@dataclass(frozen=True)
class MetricRequirement:
    """``metric(signal, *params) op threshold``."""

    name: str
    metric: str
    signal: str
    params: dict[str, float]
    op: str
    threshold: float

    @property
    def reads(self) -> tuple[str, ...]:
        """The signals the requirement reads."""
        return (self.signal,)

    def values(self, runs: Runs) -> np.ndarray:
        try:
            return metric(self.metric)(runs.scored(self.signal), runs.period_ms, **self.params)
        except ValueError as exc:
            raise ValueError(f"requirement {self.name!r}: {exc}") from None

    def satisfied(self, runs: Runs) -> np.ndarray:
        return OPS[self.op](self.values(runs), self.threshold)

    def margin(self, runs: Runs) -> np.ndarray:
        """How far each run is inside (>= 0) or outside (< 0) the threshold, in the metric's unit."""
        v = self.values(runs)
        return self.threshold - v if self.op in ("<", "<=") else v - self.threshold


@dataclass(frozen=True)
class StlRequirement:
    """An STL formula, its rtamt monitor and, for the common forms, a numpy fast path."""

    name: str
    formula: str
    signals: tuple[str, ...]
    monitor: Any = field(repr=False)
    fast: FastForm | None = None

    @property
    def reads(self) -> tuple[str, ...]:
        """The signals the requirement reads."""
        return self.signals

    def robustness(self, runs: Runs, use_fast: bool = True) -> np.ndarray:
        """Robustness at time 0 of each run, (R,); ``use_fast=False`` forces rtamt (for checks)."""
        try:
            traces = {s: runs.scored(s) for s in self.signals}
        except ValueError as exc:
            raise ValueError(f"requirement {self.name!r}: {exc}") from None
        if runs.scored_length < 2:
            raise ValueError(f"requirement {self.name!r}: STL needs runs of at least 2 scored samples")
        if self.fast is not None and use_fast:
            return self.fast.robustness(traces)
        times = list(range(runs.scored_length))
        out = np.empty(runs.count)
        for r in range(runs.count):
            data = {"time": times, **{s: traces[s][r].tolist() for s in self.signals}}
            out[r] = float(self.monitor.evaluate(data)[0][1])
        return out

    def satisfied(self, runs: Runs) -> np.ndarray:
        return self.robustness(runs) >= 0

    def margin(self, runs: Runs) -> np.ndarray:
        return self.robustness(runs)


Requirement = MetricRequirement | StlRequirement


def parse(req: RequirementSpec, signals: Collection[str]) -> Requirement:
    """The requirement, checked against the signals the runs hold; every problem is a ValueError
    naming the requirement and what is wrong."""
    if req.kind not in ("metric", "stl"):
        raise ValueError(f"requirement {req.name!r}: kind must be 'metric' or 'stl', not {req.kind!r}")
    if len(req.expr) > MAX_EXPR:
        raise ValueError(f"requirement {req.name!r}: {len(req.expr)} characters, at most {MAX_EXPR}")
    try:
        return _parse_metric(req, signals) if req.kind == "metric" else _parse_stl(req, signals)
    except (RecursionError, MemoryError):  # both parsers recurse: 5,000 nested '-' once ended in a traceback
        raise ValueError(f"requirement {req.name!r}: the expression is nested too deeply to parse") from None


#: the longest requirement text parsed: a formula is a line, and the STL parser's memory and the
#: metric parser's recursion grow with its length ('always ' 3,000 times once ran out of memory)
MAX_EXPR = 2000


def satisfied(req: RequirementSpec | Requirement, runs: Runs) -> np.ndarray:
    """Whether each run satisfies the requirement, (R,) bool."""
    parsed = parse(req, runs.signals) if isinstance(req, RequirementSpec) else req
    return np.asarray(parsed.satisfied(runs), dtype=bool)


# ---------------------------------------------------------------------- metric requirements


def _parse_metric(req: RequirementSpec, signals: Collection[str]) -> MetricRequirement:
    where = f"requirement {req.name!r}"
    try:
        tree = ast.parse(req.expr.strip(), mode="eval").body
    except SyntaxError as exc:
        raise ValueError(f"{where}: {req.expr!r} is not an expression ({exc.msg} at column {exc.offset})") from None
    if not isinstance(tree, ast.Compare) or len(tree.ops) != 1:
        raise ValueError(
            f"{where}: needs one comparison of a metric with a number, "
            f"e.g. 'max_abs_dev(color, 40) <= 35', not {req.expr!r}"
        )
    op_type = type(tree.ops[0])
    if op_type not in COMPARISONS:
        raise ValueError(f"{where}: bad operator {_op_text(tree.ops[0])!r}; use <, <=, > or >=")
    op = COMPARISONS[op_type][0]
    left, right = tree.left, tree.comparators[0]
    if isinstance(right, ast.Call) and not isinstance(left, ast.Call):
        left, right, op = right, left, FLIPPED[op]
    if not isinstance(left, ast.Call):
        raise ValueError(  # noqa: TRY004 (bad input: ValueError)
            f"{where}: one side must be a metric call like 'min(distance)', not {ast.unparse(left)!r}"
        )
    threshold = _number(right, where, "threshold")
    name, signal, params = _metric_call(left, where, signals)
    return MetricRequirement(req.name, name, signal, params, op, threshold)


def _metric_call(call: ast.Call, where: str, signals: Collection[str]) -> tuple[str, str, dict[str, float]]:
    if not isinstance(call.func, ast.Name):
        raise ValueError(f"{where}: {ast.unparse(call.func)!r} is not a metric name")  # noqa: TRY004
    name = call.func.id
    if name not in KNOWN:
        raise ValueError(f"{where}: unknown metric {name!r}; known: {', '.join(sorted(KNOWN))}")
    spec = KNOWN[name]
    if not call.args or not isinstance(call.args[0], ast.Name):
        raise ValueError(f"{where}: {name}() needs a signal name first, e.g. {name}(color)")
    signal = call.args[0].id
    if signal not in signals:
        raise ValueError(f"{where}: unknown signal {signal!r}; signals: {', '.join(signals)}")
    positional = call.args[1:]
    if len(positional) > len(spec.params):
        raise ValueError(
            f"{where}: {name}() takes at most {len(spec.params)} parameter(s) after the signal "
            f"({', '.join(spec.params) or 'none'}), got {len(positional)}"
        )
    params = {p: _number(a, where, f"{name}() parameter {p!r}") for p, a in zip(spec.params, positional)}
    for kw in call.keywords:
        if kw.arg is None or kw.arg not in spec.params:
            raise ValueError(
                f"{where}: {name}() has no parameter {kw.arg!r}; parameters: {', '.join(spec.params) or 'none'}"
            )
        if kw.arg in params:
            raise ValueError(f"{where}: {name}() parameter {kw.arg!r} is given twice")
        params[kw.arg] = _number(kw.value, where, f"{name}() parameter {kw.arg!r}")
    missing = [p for p in spec.required if p not in params]
    if missing:
        raise ValueError(
            f"{where}: {name}() needs parameter {missing[0]!r} (parameters in order: {', '.join(spec.params)})"
        )
    return name, signal, params


def _number(node: ast.expr, where: str, what: str) -> float:
    """A numeric literal, possibly signed; anything else is an error naming ``what``."""
    sign = 1.0
    inner = node
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
        inner = node.operand
    if (
        isinstance(inner, ast.Constant)
        and isinstance(inner.value, (int, float))
        and not isinstance(inner.value, bool)
        and math.isfinite(inner.value)
    ):
        return sign * float(inner.value)
    raise ValueError(f"{where}: {what} must be a finite number, not {ast.unparse(node)!r}")


def _op_text(op: ast.cmpop) -> str:
    return {ast.Eq: "==", ast.NotEq: "!=", ast.Is: "is", ast.IsNot: "is not", ast.In: "in", ast.NotIn: "not in"}.get(
        type(op), type(op).__name__
    )


# ---------------------------------------------------------------------- STL requirements

_IDENT = re.compile(r"[A-Za-z_]\w*")
_BOUND = re.compile(r"\[([^\]]*)\]")
_TEMPORAL = re.compile(r"^\s*(always|eventually)\s*(?:\[\s*(\d+)\s*:\s*(\d+)\s*\])?\s*\((.*)\)\s*$", re.DOTALL)


def _parse_stl(req: RequirementSpec, signals: Collection[str]) -> StlRequirement:
    where = f"requirement {req.name!r}"
    for bound in _BOUND.findall(req.expr):
        _check_bound(bound, where)
    used = tuple(s for s in dict.fromkeys(_IDENT.findall(req.expr)) if s in signals)
    monitor = rtamt.StlDiscreteTimeSpecification()
    for s in used:
        monitor.declare_var(s, "float")
    monitor.spec = req.expr
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)  # rtamt logs a warning before raising on an undeclared name
    try:
        monitor.parse()
    except KeyError as exc:
        raise ValueError(f"{where}: unknown signal {exc.args[0]!r}; signals: {', '.join(signals)}") from None
    except RTAMTException as exc:
        detail = str(exc).replace("RTAMT Exception: ", "").split(" expecting {")[0].strip()
        raise ValueError(f"{where}: STL syntax error in {req.expr!r}: {detail}") from None
    finally:
        logging.disable(previous)
    root = monitor.ast.specs[0]
    if type(root).__module__.startswith("rtamt.syntax.node.arithmetic") or type(root).__name__ in (
        "Variable",
        "Constant",
    ):
        raise ValueError(f"{where}: {req.expr!r} is a number, not a condition; compare it, e.g. 'color >= 5'")
    if not used:
        raise ValueError(f"{where}: {req.expr!r} reads no signal; signals: {', '.join(signals)}")
    return StlRequirement(req.name, req.expr, used, monitor, fast_form(req.expr, set(used)))


def _check_bound(bound: str, where: str) -> None:
    """``lo:hi`` with integers lo <= hi: STL bounds count samples (see the module docstring)."""
    if re.search(r"[A-Za-df-z]|[eE][^0-9+-]|[eE]$", bound):  # 1e400 is an exponent, not a unit
        raise ValueError(
            f"{where}: bound [{bound}] has a unit; STL bounds count samples of the control "
            f"period (at 40 ms, one second is 25 samples), write them as plain integers"
        )
    parts = [p.strip() for p in bound.split(":")]
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise ValueError(f"{where}: bound [{bound}] must be [lo:hi] with whole numbers of samples")
    if int(parts[0]) > int(parts[1]):
        raise ValueError(f"{where}: bound [{bound}] is empty (lower end after the upper end)")


@dataclass(frozen=True)
class FastForm:
    """``op[lo:hi](body)`` (or ``body`` alone) with ``body`` comparisons of arithmetic on signals
    joined by and/or/not: its robustness at time 0, computed over all runs at once."""

    temporal: str | None  # "always", "eventually" or None (the body at time 0)
    lo: int
    hi: int | None  # None: to the end of the run
    body: ast.expr

    def robustness(self, traces: dict[str, np.ndarray]) -> np.ndarray:
        r, t = next(iter(traces.values())).shape
        if self.temporal is None:
            return _robust(self.body, {k: v[:, :1] for k, v in traces.items()})[:, 0]
        end = t if self.hi is None else min(self.hi + 1, t)
        if self.lo >= end:  # the window lies beyond the run: vacuous, as rtamt's offline semantics
            return np.full(r, math.inf if self.temporal == "always" else -math.inf)
        rob = _robust(self.body, {k: v[:, self.lo : end] for k, v in traces.items()})
        return rob.min(axis=1) if self.temporal == "always" else rob.max(axis=1)


def fast_form(formula: str, signals: set[str]) -> FastForm | None:
    """The fast form of ``formula``, or None when it has another shape (rtamt checks it then)."""
    m = _TEMPORAL.match(formula)
    temporal, lo, hi, body_text = (
        (m.group(1), int(m.group(2) or 0), None if m.group(3) is None else int(m.group(3)), m.group(4))
        if m
        else (None, 0, None, formula)
    )
    try:
        body = ast.parse(body_text.strip(), mode="eval").body
    except SyntaxError:
        return None
    if not _is_boolean(body, signals):
        return None
    return FastForm(temporal, lo, hi, body)


def _is_boolean(node: ast.expr, signals: set[str]) -> bool:
    if isinstance(node, ast.BoolOp):
        return all(_is_boolean(v, signals) for v in node.values)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        return _is_boolean(node.operand, signals)
    if isinstance(node, ast.Compare):
        return (
            len(node.ops) == 1
            and type(node.ops[0]) in COMPARISONS
            and _is_arith(node.left, signals)
            and _is_arith(node.comparators[0], signals)
        )
    return False


def _is_arith(node: ast.expr, signals: set[str]) -> bool:
    if isinstance(node, ast.Name):
        return node.id in signals
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool)
    if isinstance(node, ast.UnaryOp):
        return isinstance(node.op, ast.USub) and _is_arith(node.operand, signals)
    if isinstance(node, ast.BinOp):
        return isinstance(node.op, (ast.Add, ast.Sub, ast.Mult)) and all(
            _is_arith(n, signals) for n in (node.left, node.right)
        )
    if isinstance(node, ast.Call):
        return (
            isinstance(node.func, ast.Name)
            and node.func.id == "abs"
            and len(node.args) == 1
            and not node.keywords
            and _is_arith(node.args[0], signals)
        )
    return False


def _robust(node: ast.expr, traces: dict[str, np.ndarray]) -> np.ndarray:
    """Robustness of a Boolean body sample by sample: comparisons give signed distances, ``and``
    the minimum, ``or`` the maximum, ``not`` the negation (rtamt's quantitative semantics)."""
    if isinstance(node, ast.BoolOp):
        parts = [_robust(v, traces) for v in node.values]
        return np.minimum.reduce(parts) if isinstance(node.op, ast.And) else np.maximum.reduce(parts)
    if isinstance(node, ast.UnaryOp):
        return -_robust(node.operand, traces)
    assert isinstance(node, ast.Compare)
    left, right = _arith(node.left, traces), _arith(node.comparators[0], traces)
    shape = next(iter(traces.values())).shape
    diff = np.broadcast_to(left - right, shape)
    return diff if isinstance(node.ops[0], (ast.Gt, ast.GtE)) else -diff


def _arith(node: ast.expr, traces: dict[str, np.ndarray]) -> np.ndarray | float:
    if isinstance(node, ast.Name):
        return traces[node.id]
    if isinstance(node, ast.Constant):
        return float(node.value)
    if isinstance(node, ast.UnaryOp):
        return -_arith(node.operand, traces)
    if isinstance(node, ast.Call):
        return np.abs(_arith(node.args[0], traces))
    assert isinstance(node, ast.BinOp)
    a, b = _arith(node.left, traces), _arith(node.right, traces)
    return a + b if isinstance(node.op, ast.Add) else a - b if isinstance(node.op, ast.Sub) else a * b

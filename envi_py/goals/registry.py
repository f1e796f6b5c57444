"""Find a goal metric by name: a standard one, a preset's, or a user's ``package.module:function``.

A user's metric has the standard signature: ``fn(trace, [period_ms,] **params) -> (R,)`` with
``trace`` (R, T). Its parameters are read from its signature (those after ``trace`` other than
``period_ms``, in order); it has no declared unit, and no scale (a caller normalising distances
uses the observed spread instead). Its output is checked on every call
(:meth:`MetricDef.__call__`), so a wrong shape is an error naming the function.
"""

from __future__ import annotations

import importlib
import inspect

from .library import STANDARD, MetricDef
from .presets import DRIVING

KNOWN: dict[str, MetricDef] = {**STANDARD, **DRIVING}


def metric(name: str) -> MetricDef:
    """The metric called ``name``; a ``module:function`` path is imported and its signature checked."""
    if name in KNOWN:
        return KNOWN[name]
    if ":" not in name:
        raise ValueError(
            f"unknown goal metric {name!r}; known: {', '.join(sorted(KNOWN))}, or a user's 'package.module:function'"
        )
    return user_metric(name)


def user_metric(path: str) -> MetricDef:
    """A user's metric from ``package.module:function``."""
    module_name, _, fn_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ValueError(f"goal metric {path!r}: cannot import module {module_name!r} ({exc})") from None
    fn = getattr(module, fn_name, None)
    if not callable(fn):
        raise ValueError(f"goal metric {path!r}: module {module_name!r} has no function {fn_name!r}")  # noqa: TRY004
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        raise ValueError(f"goal metric {path!r}: its signature cannot be read") from None
    params = list(sig.parameters.values())
    if not params or params[0].kind not in (params[0].POSITIONAL_ONLY, params[0].POSITIONAL_OR_KEYWORD):
        raise ValueError(f"goal metric {path!r}: must take the trace (runs, samples) as its first argument")
    rest = [p for p in params[1:] if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    names = tuple(p.name for p in rest if p.name != "period_ms")
    required = tuple(p.name for p in rest if p.name != "period_ms" and p.default is p.empty)
    return MetricDef(
        path, fn, names, required, uses_period=any(p.name == "period_ms" for p in rest), unit=lambda unit: ""
    )

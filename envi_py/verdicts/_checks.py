"""Input checks shared by the verdict modules: one clear ValueError naming the argument and the problem."""

from __future__ import annotations

import numbers

import numpy as np


def probability(name: str, value: float, *, open_interval: bool = True) -> float:
    """``value`` as a float strictly inside (0, 1) (or inside [0, 1] when ``open_interval`` is False)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number, got {type(value).__name__}")  # noqa: TRY004 - project rule: bad input is a ValueError
    v = float(value)
    ok = (0.0 < v < 1.0) if open_interval else (0.0 <= v <= 1.0)
    if not ok:
        bounds = "(0, 1)" if open_interval else "[0, 1]"
        raise ValueError(f"{name} must lie in {bounds}, got {value!r}")
    return v


def count(name: str, value: int, minimum: int = 0) -> int:
    """``value`` as an int >= ``minimum``; floats with an integral value are accepted, bools are not."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be an integer, got {type(value).__name__}")  # noqa: TRY004 - as above
    if isinstance(value, numbers.Integral) or float(value).is_integer():
        v = int(value)
    else:
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if v < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {v}")
    return v


def finite_vector(name: str, values: object, minimum_length: int = 1) -> np.ndarray:
    """``values`` as a 1-D float array of finite numbers with at least ``minimum_length`` entries."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numbers: {exc}") from None
    if a.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {a.shape}")
    if a.size < minimum_length:
        raise ValueError(f"{name} needs at least {minimum_length} values, got {a.size}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds {int(np.sum(~np.isfinite(a)))} NaN or infinite values")
    return a


def outcomes(name: str, values: object, minimum_length: int = 1) -> np.ndarray:
    """Goal outcomes as a 1-D bool array: bools, or numbers that are exactly 0 or 1."""
    a = finite_vector(name, values, minimum_length)
    if not np.all((a == 0) | (a == 1)):
        raise ValueError(f"{name} must be goal outcomes (0/1 or bool); found {a[(a != 0) & (a != 1)][:3].tolist()}")
    return a.astype(bool)


def unit_vector(name: str, values: object, minimum_length: int = 1) -> np.ndarray:
    """Probabilities (predictions) as a 1-D float array inside [0, 1]."""
    a = finite_vector(name, values, minimum_length)
    if np.any((a < 0) | (a > 1)):
        raise ValueError(f"{name} must be probabilities in [0, 1]; found {a[(a < 0) | (a > 1)][:3].tolist()}")
    return a

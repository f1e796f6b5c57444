"""Timing figures for the sidecar: loop period statistics and round-trip statistics."""

from __future__ import annotations

from typing import Sequence

import numpy as np


def summary(values: Sequence[float] | np.ndarray) -> dict[str, float] | None:
    """mean, sd, p50, p99 and max of a sample (None when empty), rounded to 0.001."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return None
    out = {
        "n": int(v.size),
        "mean": float(v.mean()),
        "sd": float(v.std()),
        "p50": float(np.percentile(v, 50)),
        "p99": float(np.percentile(v, 99)),
        "max": float(v.max()),
        "min": float(v.min()),
    }
    return {k: (x if k == "n" else round(x, 3)) for k, x in out.items()}


def period_stats(ticks: Sequence[int], times_ms: Sequence[float]) -> dict[str, float] | None:
    """Loop period between consecutive ticks only (a gap is not a long period), plus the rate."""
    k = np.asarray(ticks)
    t = np.asarray(times_ms, dtype=np.float64)
    if k.size < 2:
        return None
    consecutive = np.diff(k) == 1
    periods = np.diff(t)[consecutive]
    s = summary(periods)
    if s is None:
        return None
    s["rate_hz"] = round(1000.0 / s["mean"], 3) if s["mean"] > 0 else None
    return s


def gaps(ticks: Sequence[int], n_ticks: int) -> list[list[int]]:
    """Missing tick ranges ``[first, last]`` between 0 and ``n_ticks - 1``."""
    out: list[list[int]] = []
    expect = 0
    for k in list(ticks) + [n_ticks]:
        if k > expect:
            out.append([expect, k - 1])
        expect = max(expect, k + 1)
    return out

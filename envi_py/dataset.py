"""From logs to training pairs: per-column normalisation, sliding windows, splits by log.

A window is the last ``l`` rows of (states, actions), flattened row-major to ``l*(|s|+|a|)``
(oldest row first, as the paper's Figure 4); its target is the next row's states. Splits are made
between whole logs, never between windows of one log, so no test window overlaps a training one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from .logs import Log, LogSchema


@dataclass(frozen=True)
class Normaliser:
    """Affine map of each column onto [-1, 1]: ``z = (v - centre) / half``."""

    low: np.ndarray
    high: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        return (self.high + self.low) / 2

    @property
    def half(self) -> np.ndarray:
        return (self.high - self.low) / 2

    def encode(self, v: np.ndarray) -> np.ndarray:
        return (v - self.centre) / self.half

    def decode(self, z: np.ndarray) -> np.ndarray:
        return z * self.half + self.centre

    @staticmethod
    def fit(logs: Sequence[Log]) -> "Normaliser":
        """Min and max of each column over the (training) logs. A constant column gets +-1 around
        its value so that it still encodes to 0 rather than dividing by zero."""
        allv = np.concatenate([lg.values for lg in logs], axis=0)
        low, high = allv.min(axis=0), allv.max(axis=0)
        flat = high - low < 1e-12
        return Normaliser(np.where(flat, low - 1, low), np.where(flat, high + 1, high))

    @staticmethod
    def from_schema(schema: LogSchema) -> "Normaliser":
        """The declared valid ranges; every channel must declare a finite one."""
        lo = np.array([c.low for c in schema.channels], dtype=np.float64)
        hi = np.array([c.high for c in schema.channels], dtype=np.float64)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
            raise ValueError("declared ranges are not all finite and non-empty; fit the normaliser on data instead")
        return Normaliser(lo, hi)

    def to_json(self) -> dict[str, Any]:
        return {"low": self.low.tolist(), "high": self.high.tolist()}

    @staticmethod
    def from_json(d: dict[str, Any]) -> "Normaliser":
        return Normaliser(np.asarray(d["low"], dtype=np.float64), np.asarray(d["high"], dtype=np.float64))


def windows(values: np.ndarray, history: int) -> np.ndarray:
    """All windows of a (T, C) array as a (T-history+1, history, C) view; no copy."""
    return np.lib.stride_tricks.sliding_window_view(values, history, axis=0).transpose(0, 2, 1)


def log_pairs(z: np.ndarray, history: int, n_state: int) -> tuple[np.ndarray, np.ndarray]:
    """Training pairs of one normalised log: X (T-l, l*C) and Y (T-l, |s|)."""
    w = windows(z[:-1], history)
    return w.reshape(w.shape[0], -1), z[history:, :n_state]


@dataclass
class Dataset:
    """Per-log training pairs, kept per log because the paper's BC loop steps once per log."""

    norm: Normaliser
    history: int
    n_state: int
    X: list[np.ndarray]
    Y: list[np.ndarray]
    z: list[np.ndarray]  # each whole normalised log (T, C); GAIL rolls out from these

    @staticmethod
    def build(logs: Sequence[Log], history: int, norm: Normaliser | None = None) -> "Dataset":
        norm = norm or Normaliser.fit(logs)
        n_state = logs[0].states.shape[1]
        zs, xs, ys = [], [], []
        for lg in logs:
            if len(lg) <= history:
                raise ValueError(f"{lg.name}: {len(lg)} rows, need more than the history {history}")
            z = norm.encode(lg.values).astype(np.float32)
            x, y = log_pairs(z, history, n_state)
            zs.append(z), xs.append(x), ys.append(y)
        return Dataset(norm, history, n_state, xs, ys, zs)

    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate(self.X), np.concatenate(self.Y)


def split_logs(logs: Sequence[Log], fractions: Sequence[float], seed: int) -> list[list[Log]]:
    """Split whole logs into groups of the given fractions, after a seeded shuffle.

    Each non-zero fraction gets at least one log when there are enough logs.
    """
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(logs))
    counts = [int(round(f * len(logs))) for f in fractions]
    for i, f in enumerate(fractions):
        if f > 0 and counts[i] == 0 and len(logs) > sum(counts):
            counts[i] = 1
    counts[-1] = len(logs) - sum(counts[:-1])
    if counts[-1] < 0:
        raise ValueError(f"cannot split {len(logs)} logs into {fractions}")
    out, pos = [], 0
    for c in counts:
        out.append([logs[i] for i in sorted(order[pos:pos + c])])
        pos += c
    return out

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


#: Derived per-row input channels an effect may need (see :class:`envi_py.model.ModelConfig`):
#: ``dt`` the interval from this row to the next, relative to the nominal period (sampling jitter);
#: ``phase`` the position in the run, -1 at the first row to +1 at ``phase_rows`` and after (drift);
#: ``play`` where an actuator with play sits relative to the row's first action (backlash): a
#: hysteresis of the whole action history, which no window of recent rows holds.
EXTRA_CHANNELS = ("dt", "phase", "play")


def play_offsets(a: np.ndarray, width: float, start: np.ndarray | float | None = None) -> np.ndarray:
    """Backlash filter of command sequences ``a`` (..., T): an actuator with play ``width`` stays
    put until the command pushes it from one side of the play (``p = clip(p, a - w/2, a + w/2)``);
    returns its offset from the command per row, (..., T). It starts at ``start`` (the position
    before the first row; by default the first command). Position = command + offset, so a row
    that holds the offset is all a later row needs to continue the filter."""
    a = np.asarray(a, dtype=np.float64)
    out = np.empty_like(a)
    if a.shape[-1] == 0:
        return out
    p = np.array(a[..., 0] if start is None else np.broadcast_to(start, a.shape[:-1]), dtype=np.float64)
    h = width / 2
    for t in range(a.shape[-1]):
        p = np.clip(p, a[..., t] - h, a[..., t] + h)
        out[..., t] = p - a[..., t]
    return out


def extra_channels(
    time_ms: np.ndarray,
    names: Sequence[str],
    period_ms: float,
    phase_rows: int,
    first_row: int = 0,
    action: np.ndarray | None = None,
    play_width: float = 0.0,
) -> np.ndarray:
    """The derived channels of rows ``first_row...`` of a log, (T, len(names)), on a [-1, 1]-like scale.

    ``play`` needs the log's first action, normalised (``action``, (T,)), and the play's full width
    as a fraction of that action's range (``play_width``); the filter starts at the first row, as a
    simulation from the log's initial window does."""
    cols = []
    for name in names:
        if name == "dt":
            dt = np.append(np.diff(time_ms), period_ms)
            cols.append(np.clip(dt / period_ms - 1.0, -1.0, 3.0))
        elif name == "phase":
            cols.append(np.minimum(np.arange(first_row, first_row + len(time_ms)) / phase_rows, 1.0) * 2 - 1)
        elif name == "play":
            if action is None or len(action) != len(time_ms):
                raise ValueError("the 'play' channel needs the action of every row")
            cols.append(play_offsets(action, 2.0 * play_width))  # the normalised range is 2 wide
        else:
            raise ValueError(f"unknown extra channel {name!r}; known: {', '.join(EXTRA_CHANNELS)}")
    return np.stack(cols, axis=1) if cols else np.zeros((len(time_ms), 0))


def actuator_position(rows: np.ndarray, n_state: int, channels: int, extras: Sequence[str]) -> np.ndarray:
    """Where the actuator with play sits after the last of the normalised model ``rows`` (..., n, W):
    its command plus the row's ``play`` offset. The filter of the next rows continues from it."""
    last = rows[..., -1, :]
    return last[..., n_state] + last[..., channels + list(extras).index("play")]


def interval_quantiles(logs: Sequence[Log], period_ms: float, n: int = 101) -> tuple[float, ...]:
    """``n`` quantiles of the ``dt`` channel over the logs' real intervals: a model that takes the
    interval as input is simulated with intervals drawn from these, not with the nominal one."""
    dt = np.concatenate([np.diff(lg.time) for lg in logs if len(lg) > 1])
    rel = np.clip(dt / period_ms - 1.0, -1.0, 3.0)
    return tuple(float(q) for q in np.quantile(rel, np.linspace(0, 1, n)))


def context_of(window_z: np.ndarray, n_state: int) -> np.ndarray:
    """Per-run context from the normalised initial window(s) (..., l, C): mean and spread of each state.

    It tells the model which run it is in (a faster robot swings wider) for all of the run, not only
    while sigma_0 is still inside the sliding window.
    """
    s = window_z[..., :n_state]
    return np.concatenate([s.mean(axis=-2), s.std(axis=-2)], axis=-1)


def log_pairs(
    z: np.ndarray, history: int, n_state: int, context: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Training pairs of one normalised log: X (T-l, l*C [+ context]) and Y (T-l, |s|)."""
    w = windows(z[:-1], history)
    x = w.reshape(w.shape[0], -1)
    if context is not None:
        x = np.concatenate([x, np.broadcast_to(context, (x.shape[0], context.shape[-1]))], axis=1)
    return x, z[history:, :n_state]


@dataclass
class Dataset:
    """Per-log training pairs, kept per log because the paper's BC loop steps once per log (per piece
    of a log with lost rows, when cut at its breaks)."""

    norm: Normaliser
    history: int
    n_state: int
    X: list[np.ndarray]
    Y: list[np.ndarray]
    z: list[np.ndarray]  # each normalised log or piece (T, C [+ extras]); GAIL rolls out from these
    origin: list[tuple[int, int]]  # per entry: the index of its log and the log row it starts at
    #: per entry: the run context of its log, from the log's first rows as simulation computes it (a
    #: piece after a break keeps its run's context, not one of its own rows)
    contexts: list[np.ndarray]

    @staticmethod
    def build(
        logs: Sequence[Log],
        history: int,
        norm: Normaliser | None = None,
        extras: Sequence[str] = (),
        period_ms: float = 40.0,
        phase_rows: int = 100,
        context: bool = False,
        play_width: float = 0.0,
        cut_at_breaks: bool = False,
    ) -> "Dataset":
        """Pairs of every log; ``extras`` and ``context`` as declared by the model's config.

        ``cut_at_breaks`` (training): a log with lost rows (its ``meta.breaks``) gives the pieces
        between them, as logs of their own, since a window across a break would teach a jump the system
        never made (pieces of ``history`` rows or fewer give no pair and are left out). Without it the
        pairs line up with each log's rows, as a diagnosis of one-step residuals needs."""
        norm = norm or Normaliser.fit(logs)
        n_state = logs[0].states.shape[1]
        zs, xs, ys, origin, contexts = [], [], [], [], []
        for li, lg in enumerate(logs):
            if len(lg) <= history:
                raise ValueError(f"{lg.name}: {len(lg)} rows, need more than the history {history}")
            zv = norm.encode(lg.values)
            ex = extra_channels(lg.time, extras, period_ms, phase_rows, action=zv[:, n_state], play_width=play_width)
            rows = np.concatenate([zv, ex], axis=1)
            run_context = context_of(rows[:history].astype(np.float32), n_state)
            cuts = [b for b in lg.meta.breaks if 0 < b < len(rows)] if cut_at_breaks else []
            pieces = [(a, p) for a, p in zip([0, *cuts], np.split(rows, cuts)) if len(p) > history]
            if not pieces:
                raise ValueError(f"{lg.path or lg.name}: no stretch of more than {history} rows between its lost rows")
            for first, piece in pieces:
                origin.append((li, first))
                contexts.append(run_context)
                z = piece.astype(np.float32)
                x, y = log_pairs(z, history, n_state, run_context if context else None)
                zs.append(z), xs.append(x), ys.append(y)
        return Dataset(norm, history, n_state, xs, ys, zs, origin, contexts)

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
        out.append([logs[i] for i in sorted(order[pos : pos + c])])
        pos += c
    return out

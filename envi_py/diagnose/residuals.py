"""One-step residuals: the model's prediction on real windows against the real next state.

Each residual carries what the candidate-effect tests condition on: the run it came from, its row,
the state and action it was predicted from, the actual sampling interval, and the inputs that lie
*before* the window (for memory/delay). Residuals are in physical units of the first state.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np
import torch

from ..dataset import play_offsets
from ..logs import Log
from ..model import Checkpoint

#: How many rows before the window the memory/delay test looks at.
BEYOND = 6


@dataclass
class Residuals:
    """Flat arrays, one entry per predicted row."""

    r: np.ndarray  # real next state - predicted mean (physical units)
    pred_std: np.ndarray | None  # predicted standard deviation (Gaussian head), physical units
    predicted: np.ndarray  # the predicted mean, after the model's post-processing
    real_next: np.ndarray
    state: np.ndarray  # last state of the window
    action: np.ndarray  # last action of the window
    run: np.ndarray  # index of the log
    row: np.ndarray  # row index of the predicted state within its log
    dt: np.ndarray  # actual interval (ms) from the window's last row to the predicted row
    window: np.ndarray  # the window (N, l*C) in normalised units
    beyond: np.ndarray  # (N, BEYOND*C) normalised rows before the window; NaN where the log has none
    play: np.ndarray  # (N, len(PLAY_WIDTHS)): where an actuator with play of each width would sit
    #                   relative to the last action of the window (see :func:`play_offsets`)

    def __len__(self) -> int:
        return int(self.r.shape[0])

    def ms_by_run(self, runs: int) -> np.ndarray:
        """Mean square residual of each of ``runs`` logs (NaN for a log without residuals)."""
        return np.array(
            [float(np.mean(self.r[self.run == i] ** 2)) if np.any(self.run == i) else np.nan for i in range(runs)]
        )

    @cached_property
    def pairs(self) -> "Pairs":
        """Each residual matched with its nearest window from another run (see :class:`Pairs`)."""
        return Pairs.match(self)


@dataclass(frozen=True)
class Pairs:
    """Residual ``i`` paired with ``j``, the residual whose window is nearest to ``i``'s among the
    other runs (normalised units).

    Why: a model's misfit is a smooth function of its window, so it cancels in ``r_i - r_j``; what
    is left is what the window does not determine: noise, and anything that differs between the two
    (time in the run, the sampling interval, the rows before the window, the run itself). The
    candidate tests regress these differences on the differences of the quantity they suspect,
    so the misfit of a well-structured model is not mistaken for an effect.
    """

    i: np.ndarray
    j: np.ndarray
    d2: np.ndarray  # squared window distance of the pair

    @staticmethod
    def match(res: "Residuals", k: int = 8) -> "Pairs":
        from scipy.spatial import cKDTree

        w = np.asarray(res.window, dtype=np.float64)
        k = min(k, len(w))
        dist, idx = cKDTree(w).query(w, k=k)
        dist, idx = dist.reshape(len(w), k), idx.reshape(len(w), k)
        other = res.run[idx] != res.run[:, None]
        first = np.argmax(other, axis=1)
        ok = other[np.arange(len(w)), first]
        i = np.flatnonzero(ok)
        j = idx[i, first[ok]]
        return Pairs(i, j, dist[i, first[ok]] ** 2)

    def __len__(self) -> int:
        return int(self.i.shape[0])


#: Widths of actuator play tried by the backlash test, as fractions of the action's training range:
#: 5% to 80% in steps of sqrt(2), so the true width is never far from one (a play filter of the
#: wrong width leaves part of the hysteresis to the linear memory test).
PLAY_WIDTHS = tuple(round(0.05 * 2 ** (k / 2), 4) for k in range(9))


@torch.no_grad()
def one_step_residuals(ckpt: Checkpoint, logs: Sequence[Log]) -> Residuals:
    """Feed every real window of ``logs`` to the model and collect the residuals."""
    cfg = ckpt.config
    data = ckpt.dataset(logs)
    hist, ns, ch = cfg.history, cfg.n_state, cfg.channels
    parts: dict[str, list[np.ndarray]] = {k: [] for k in Residuals.__dataclass_fields__}
    scale = ckpt.norm.half[:ns]
    for i, (lg, x) in enumerate(zip(logs, data.X)):
        mean, log_std = ckpt.model(torch.from_numpy(np.ascontiguousarray(x)))
        mean = mean.numpy().astype(np.float64)
        pred = ckpt.decode_states(mean)[:, 0]
        n = len(pred)
        rows = np.arange(hist, hist + n)
        real_next = lg.states[hist:, 0]
        parts["r"].append(real_next - pred)
        parts["pred_std"].append(np.exp(log_std.numpy()[:, 0]) * scale[0] if log_std is not None else np.zeros(n))
        parts["predicted"].append(pred)
        parts["real_next"].append(real_next)
        parts["state"].append(lg.states[hist - 1 : -1, 0])
        parts["action"].append(lg.actions[hist - 1 : -1, 0])
        parts["run"].append(np.full(n, i))
        parts["row"].append(rows)
        parts["dt"].append(np.diff(lg.time)[hist - 1 :])
        parts["window"].append(x[:, : hist * cfg.row_width])
        z = ckpt.norm.encode(lg.values)
        beyond = np.full((n, BEYOND * ch), np.nan)
        for j, t in enumerate(rows):
            first = t - hist  # first row of the window
            lo = max(0, first - BEYOND)
            block = z[lo:first]
            if len(block):
                beyond[j, (BEYOND - len(block)) * ch :] = block.ravel()
        parts["beyond"].append(beyond)
        span = 2 * float(ckpt.norm.half[ns])  # the first action's training range
        play = np.stack([play_offsets(lg.actions[:, 0], f * span) for f in PLAY_WIDTHS], axis=1)
        parts["play"].append(play[hist - 1 : -1])
    out = {k: np.concatenate(v) for k, v in parts.items()}
    if cfg.head != "gaussian":
        out["pred_std"] = None
    return Residuals(**out)

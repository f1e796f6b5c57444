"""One-step residuals: the model's prediction on real windows against the real next state.

Each residual carries what the candidate-effect tests condition on: the run it came from, its row,
the state and action it was predicted from, the actual sampling interval, and the inputs that lie
*before* the window (for memory/delay). Residuals are in physical units of the first state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..logs import Log
from ..model import Checkpoint
from ..simulate import post_process
from ..train.common import dataset_for

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
    since_change: np.ndarray  # rows since the last action change (0 = changed on the last row)
    change_dir: np.ndarray  # sign of that last action change (0 if none seen)

    def __len__(self) -> int:
        return int(self.r.shape[0])


@torch.no_grad()
def one_step_residuals(ckpt: Checkpoint, logs: Sequence[Log]) -> Residuals:
    """Feed every real window of ``logs`` to the model and collect the residuals."""
    cfg = ckpt.config
    data = dataset_for(ckpt, logs)
    hist, ns, ch = cfg.history, cfg.n_state, cfg.channels
    parts: dict[str, list[np.ndarray]] = {k: [] for k in Residuals.__dataclass_fields__}
    scale = ckpt.norm.half[:ns]
    for i, (lg, x) in enumerate(zip(logs, data.X)):
        mean, log_std = ckpt.model(torch.from_numpy(np.ascontiguousarray(x)))
        mean = mean.numpy().astype(np.float64)
        phys = ckpt.norm.decode(np.concatenate([mean, np.zeros((len(mean), ch - ns))], axis=1))[:, :ns]
        pred = post_process(phys, ckpt)[:, 0]
        n = len(pred)
        rows = np.arange(hist, hist + n)
        real_next = lg.states[hist:, 0]
        parts["r"].append(real_next - pred)
        parts["pred_std"].append(np.exp(log_std.numpy()[:, 0]) * scale[0] if log_std is not None else np.zeros(n))
        parts["predicted"].append(pred)
        parts["real_next"].append(real_next)
        parts["state"].append(lg.states[hist - 1:-1, 0])
        parts["action"].append(lg.actions[hist - 1:-1, 0])
        parts["run"].append(np.full(n, i))
        parts["row"].append(rows)
        parts["dt"].append(np.diff(lg.time)[hist - 1:])
        parts["window"].append(x[:, :hist * cfg.row_width])
        z = ckpt.norm.encode(lg.values)
        beyond = np.full((n, BEYOND * ch), np.nan)
        for j, t in enumerate(rows):
            first = t - hist  # first row of the window
            lo = max(0, first - BEYOND)
            block = z[lo:first]
            if len(block):
                beyond[j, (BEYOND - len(block)) * ch:] = block.ravel()
        parts["beyond"].append(beyond)
        a = lg.actions[:, 0]
        change = np.concatenate([[0.0], np.sign(np.diff(a))])
        last_idx = -1
        since, direction = np.empty(len(a)), np.empty(len(a))
        for t in range(len(a)):
            if change[t] != 0:
                last_idx = t
            since[t] = t - last_idx if last_idx >= 0 else 10**6
            direction[t] = change[last_idx] if last_idx >= 0 else 0.0
        parts["since_change"].append(since[hist - 1:-1])
        parts["change_dir"].append(direction[hist - 1:-1])
    out = {k: np.concatenate(v) for k, v in parts.items()}
    if cfg.head != "gaussian":
        out["pred_std"] = None
    return Residuals(**out)

"""The shape of a Gaussian head's step noise, fitted after training: normal, or a heavier-tailed
Student-t of the same variance.

A Gaussian head is trained by the Gaussian likelihood, which estimates each step's mean and variance
consistently whatever the noise's shape; what it cannot say is how heavy the tails are. On the real
lane-keeping logs they matter: the comfort metric (a run's largest jerk) has a heavy tail at x = 10
that normal draws never reach (simulated sd 3.1 against 7.3 real), and unit-variance Student-t draws
with 3-6 degrees of freedom reach it (sd 6.6-8.5) without adding spread elsewhere.

The degrees of freedom are chosen per state by maximum likelihood of the standardised one-step
errors ``(y - mean) / std`` of held-out windows (the validation logs; the training logs when there
are none, whose errors are smaller and lighter-tailed) under a unit-variance Student-t, over the
whole numbers :data:`~envi_py.model.MIN_DOF`..:data:`~envi_py.model.MAX_DOF` and the normal
(scipy.stats for the densities). A saturating sensor's limit readings are left out, as the value
head's training leaves them out: the event head draws those.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from scipy import stats

from ..logs import Log
from ..model import MAX_DOF, MIN_DOF, Checkpoint


def standardised_errors(ckpt: Checkpoint, logs: Sequence[Log]) -> list[np.ndarray]:
    """Per state: the one-step errors of every window of ``logs`` over the head's predicted std (its
    limit readings left out)."""
    data = ckpt.dataset(logs, cut_at_breaks=True)
    x = torch.from_numpy(np.ascontiguousarray(np.concatenate(data.X)))
    y = np.concatenate(data.Y)
    with torch.no_grad():
        mean, log_std, _ = ckpt.model.heads(x)
    if log_std is None:
        raise ValueError("the step-noise shape is fitted for a Gaussian head only")
    r = (y - mean.numpy()) / log_std.exp().numpy()
    keep = np.ones_like(r, dtype=bool)
    events = ckpt.limit_event_targets(y)
    for k, (i, _) in enumerate(ckpt.config.limit_events):
        keep[:, i] = ~events[:, k]
    return [r[keep[:, i], i].astype(np.float64) for i in range(r.shape[1])]


def dof_log_likelihoods(errors: np.ndarray) -> dict[int, float]:
    """Log-likelihood of standardised errors under each unit-variance Student-t (key nu) and the
    normal (key 0)."""
    out = {0: float(np.sum(stats.norm.logpdf(errors)))}
    for nu in range(MIN_DOF, MAX_DOF + 1):
        out[nu] = float(np.sum(stats.t.logpdf(errors, df=nu, scale=np.sqrt((nu - 2) / nu))))
    return out


def fit_noise_dof(ckpt: Checkpoint, logs: Sequence[Log]) -> tuple[tuple[int, ...], dict[str, Any]]:
    """Each state's degrees of freedom (0: normal) and the record of the fit (per state: windows,
    chosen nu, log-likelihood gain over the normal)."""
    dof, record = [], []
    for name, errors in zip(ckpt.schema.states, standardised_errors(ckpt, logs)):
        if len(errors) < 2:
            dof.append(0)
            record.append({"state": name.name, "windows": int(len(errors)), "dof": 0, "gain_over_normal": 0.0})
            continue
        ll = dof_log_likelihoods(errors)
        best = max(ll, key=lambda k: ll[k])
        dof.append(best)
        record.append(
            {
                "state": name.name,
                "windows": int(len(errors)),
                "dof": best,
                "gain_over_normal": ll[best] - ll[0],
                "error_sd": float(np.std(errors)),
            }
        )
    return tuple(dof), {"states": record, "logs": [lg.name for lg in logs]}


def with_step_noise(ckpt: Checkpoint, step_noise: str, val_logs: Sequence[Log], train_logs: Sequence[Log]) -> None:
    """Give a trained checkpoint its step-noise shape in place (``gaussian``: none to fit), and record
    it: the setting in the hyper-parameters, the fit beside the epoch selection. ``step_noise`` is one
    of :data:`~envi_py.system.STEP_NOISES` (:func:`envi_py.train.train` checks it before training)."""
    if not ckpt.config.stochastic or ckpt.config.kind != "mlp":
        return  # nothing is drawn from a step noise
    ckpt.record.hyper["step_noise"] = step_noise
    if step_noise == "gaussian":
        return
    dof, record = fit_noise_dof(ckpt, val_logs or train_logs)
    ckpt.config.noise_dof = dof if any(dof) else ()
    ckpt.record.selection["step_noise"] = {**record, "on": "validation" if val_logs else "training"}

"""The shape of a Gaussian head's step noise, fitted after training: normal, or a heavier-tailed
Student-t of the same variance.

A Gaussian head is trained by the Gaussian likelihood, which estimates each step's mean and variance
consistently whatever the noise's shape; what it cannot say is how heavy the tails are. On the real
lane-keeping logs they matter: the comfort metric (a run's largest jerk) has a heavy tail at x = 10
that normal draws never reach (simulated sd 3.1 against 7.3 real), and unit-variance Student-t draws
with 3-6 degrees of freedom reach it without adding spread elsewhere.

The degrees of freedom are fitted in closed loop, not one step ahead. Each held-out log (the
validation logs; the training logs when there are none) is simulated from its sigma_0 with every
candidate shape (:data:`CANDIDATES`), and a state's shape is the one whose pooled absolute third
differences ``|s[t+3] - 3 s[t+2] + 3 s[t+1] - s[t]|`` are closest to the real logs' (two-sample
Kolmogorov-Smirnov distance, ``scipy.stats.ks_2samp``). Why the third difference: it all but
cancels a smooth trajectory and multiplies white step noise's variance by 20, so its distribution
is the closed loop's noise, tails included, whatever the dynamics. Why closed loop: on the real
lane-keeping logs the maximum likelihood of the one-step standardised errors chose 4-21 degrees of
freedom, while the simulated runs matched the real ones' jerks at 3-4; fitted this way the mean KLD
over the five versions went from 1.71 to 1.18 at n = 3 training logs per version and from 0.98 to
0.94 at n = 20, the same 9 models each (README, "Fidelity on the real logs").

States are fitted in order, each with the earlier states at their fitted shape and the later ones
normal. A saturating sensor's limit readings are left out (the event head draws those), as are
differences that span a break in a log.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats

from ..logs import Log
from ..model import Checkpoint
from ..simulate import simulate_versions

#: the shapes tried, simplest first (a tie keeps the earlier): 0 is the normal, the rest Student-t
#: degrees of freedom (see :data:`~envi_py.model.MIN_DOF`)
CANDIDATES: tuple[int, ...] = (0, 20, 12, 8, 6, 5, 4, 3)
#: simulated runs per held-out log for each candidate
RUNS_PER_LOG = 10
#: fewer real third differences than this for a state and it keeps normal draws: a tail needs rows
MIN_ROWS = 30


def third_differences(logs: Sequence[Log], state: int, start: int, limits: Sequence[float]) -> np.ndarray:
    """Absolute third differences of state ``state`` over rows ``start`` onwards of every log, pooled;
    those whose four rows touch a limit reading (``limits``) or span one of the log's breaks left out."""
    out = []
    for lg in logs:
        s = lg.states[start:, state]
        if len(s) < 4:
            continue
        keep = np.ones(len(s) - 3, dtype=bool)
        for level in limits:
            at = np.isclose(s, level)
            keep &= ~(at[:-3] | at[1:-2] | at[2:-1] | at[3:])
        for b in lg.meta.breaks:  # row b does not follow row b - 1: no difference may span the two
            j = b - start
            keep[max(0, j - 3) : max(0, j)] = False
        out.append(np.abs(np.diff(s, 3))[keep])
    return np.concatenate(out) if out else np.zeros(0)


def fit_noise_dof(ckpt: Checkpoint, logs: Sequence[Log]) -> tuple[tuple[int, ...], dict[str, Any]]:
    """Each state's degrees of freedom (0: normal) and the record of the fit (per state: real and
    simulated differences, chosen shape, each candidate's KS distance)."""
    hist = ckpt.config.history
    logs = [lg for lg in logs if len(lg) >= hist + 4]
    seed = ckpt.record.seed
    limits = {i: [] for i in range(ckpt.config.n_state)}
    for i, level in ckpt.config.limit_events:
        limits[i].append(level)
    dof = [0] * ckpt.config.n_state
    record = []
    before = ckpt.config.noise_dof
    try:
        for i, name in enumerate(ckpt.schema.states):
            real = third_differences(logs, i, hist, limits[i])
            if len(real) < MIN_ROWS:
                record.append({"state": name.name, "real_differences": int(len(real)), "dof": 0, "ks": {}})
                continue
            ks: dict[str, float] = {}  # by candidate, "0" the normal
            for nu in CANDIDATES:
                set_dof(ckpt, [*dof[:i], nu, *([0] * (len(dof) - i - 1))])
                sims = simulate_versions(ckpt, logs, runs=RUNS_PER_LOG, seed=seed)
                ks[str(nu)] = float(stats.ks_2samp(real, third_differences(sims, i, hist, limits[i])).statistic)
            dof[i] = min(CANDIDATES, key=lambda nu: ks[str(nu)])  # the first of equals: the simplest
            record.append({"state": name.name, "real_differences": int(len(real)), "dof": dof[i], "ks": ks})
    finally:
        ckpt.config.noise_dof = before  # the fit tries shapes on the model; it leaves it as it found it
    return tuple(dof), {
        "states": record,
        "logs": [lg.name for lg in logs],
        "runs_per_log": RUNS_PER_LOG,
        "statistic": "KS distance of pooled |third difference|, simulated (closed loop) vs real",
    }


def set_dof(ckpt: Checkpoint, dof: Sequence[int]) -> None:
    """Make the model draw step noise of shape ``dof`` (all zero: normal), in place."""
    ckpt.config.noise_dof = tuple(dof) if any(dof) else ()


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
    set_dof(ckpt, dof)
    ckpt.record.selection["step_noise"] = {**record, "on": "validation" if val_logs else "training"}

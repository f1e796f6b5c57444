"""What-if tests: would the model fit the real logs if its inputs first passed through an effect?

When the logs come from a world the model was not trained on (verification against a robot that
has changed), most of the one-step residual is misfit: a smooth function of the window, which
cancels between look-alike windows, where the pair tests of :mod:`.effects` look. What the misfit
still shows is its *form*. An actuator that lags its commands is exactly a model fed lagged
commands: if passing the logged commands through a delay or a first-order lag before the model
removes most of the residual mean square, the actuator lags. No retraining is needed, and a model
that already fits its logs only gets worse under such a transform, so it rarely fires by chance.

Not every effect has a specific what-if. Shrinking the commands (an actuator's play under
reversals) also imitates anything that weakens the response (a sagging battery, a clipping sensor),
so backlash keeps to its pair test.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np
from scipy import stats

from ..logs import Log
from ..model import Checkpoint
from .residuals import ResidualSet, one_step_residuals

#: A transform of one log's action columns, (T, n_action) -> (T, n_action), and its description.
Transform = tuple[str, Callable[[np.ndarray], np.ndarray]]


@dataclass(frozen=True)
class WhatIf:
    """The transform that removed the most of the one-step residual mean square."""

    share: float  # part of the residual mean square removed (ratio of means over runs)
    p: float  # one-sided paired t-test over runs, Bonferroni over the transforms tried
    label: str  # which transform

    @staticmethod
    def none(why: str) -> "WhatIf":
        return WhatIf(0.0, 1.0, why)


def delayed(a: np.ndarray, k: int) -> np.ndarray:
    """Commands ``k`` rows late (the first command held before the log starts)."""
    return np.concatenate([np.repeat(a[:1], k, axis=0), a[:-k]]) if k else a


def lagged(a: np.ndarray, tau_rows: float) -> np.ndarray:
    """Commands through a first-order lag of time constant ``tau_rows`` rows, starting settled."""
    alpha = 1.0 - np.exp(-1.0 / tau_rows)
    out = np.empty_like(a, dtype=np.float64)
    y = np.asarray(a[0], dtype=np.float64)
    for t in range(len(a)):
        y = y + alpha * (a[t] - y)
        out[t] = y
    return out


#: The actuator-lag what-ifs: pure delays of 1-3 rows and first-order lags of 0.5-13 rows.
LAG_ROWS = (0.5, 1, 2, 3, 5, 8, 13)
ACTUATOR_LAGS: tuple[Transform, ...] = tuple(
    [(f"a delay of {k} row{'s' * (k > 1)}", lambda a, k=k: delayed(a, k)) for k in (1, 2, 3)]
    + [(f"a first-order lag of {tau:g} rows", lambda a, tau=tau: lagged(a, tau)) for tau in LAG_ROWS]
)


def _on_column(a: np.ndarray, j: int, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    out = np.array(a, dtype=np.float64)
    out[:, j] = fn(out[:, j : j + 1]).ravel()
    return out


def actuator_lags(actions: Sequence[str]) -> tuple[Transform, ...]:
    """The actuator-lag what-ifs for these actions: with one action, :data:`ACTUATOR_LAGS`; with
    several, each lag on each action alone ("a delay of 1 row on steering"), since one actuator
    may lag while another does not."""
    if len(actions) == 1:
        return ACTUATOR_LAGS
    return tuple(
        (f"{label} on {name}", lambda a, fn=fn, j=j: _on_column(a, j, fn))
        for j, name in enumerate(actions)
        for label, fn in ACTUATOR_LAGS
    )


def input_what_if(
    ckpt: Checkpoint, logs: Sequence[Log], res: ResidualSet, transforms: Sequence[Transform]
) -> list[WhatIf]:
    """Feed the model each transform of the logged commands; per state channel, keep the one that
    removes the most of that channel's residual mean square (``res``: the residuals of the
    untransformed ``logs``). Runs are independent, so the p-value pairs the per-run mean squares."""
    if len(logs) < 3:
        return [WhatIf.none("too few runs")] * len(res.states)
    base = [s.ms_by_run(len(logs)) for s in res.states]
    best = [WhatIf.none("no transform of the commands helps the model")] * len(res.states)
    for label, fn in transforms:
        changed = one_step_residuals(ckpt, [replace(lg, actions=fn(lg.actions)) for lg in logs])
        for k, s in enumerate(changed.states):
            ms = s.ms_by_run(len(logs))
            gain = base[k] - ms
            sd = float(gain.std(ddof=1))
            t = float(gain.mean()) / (sd / np.sqrt(len(gain))) if sd > 0 else 0.0
            share = 1.0 - float(ms.mean()) / max(float(base[k].mean()), 1e-300)
            if share > best[k].share:
                best[k] = WhatIf(share, min(1.0, float(stats.t.sf(t, len(gain) - 1)) * len(transforms)), label)
    return best

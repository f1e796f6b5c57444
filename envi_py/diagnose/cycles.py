"""Where the simulated runs settle into an exact repeating cycle more often than the real runs do.

A model is a map from a window of rows to the next state. A deterministic one whose readings are
rounded to the sensor's resolution is a map on a grid. Once a window repeats, the run repeats it
for ever. A real loop whose hidden state drifts by less than the sensor's resolution per cycle never
repeats exactly: its readings keep moving one step now and then.

On the clean steered twin (bang-bang x = 30, seeds 100-107, 20 held-out logs each), this check
finds 138 of 160 runs of the deterministic models settled, against 26 of 160 real runs; it is
significant at 7 of the 8 seeds. In a narrower probe (an exact period of 2 rows over the last 40
readings), 87 of 160 runs settled against 3 of 160 real runs, and the last 40 readings held 2
distinct values against 9 in the real runs (medians). These models sit at 1.4-3.1x the fair floor
on their own world. Keeping the model's window unrounded halves those 87 runs to 43; that probe is
not in the code (README, "What keeps the steered models off the floor"). The same models with the
Gaussian head settle in none of 160 runs. Neither head's models settle on the diffdrive twin,
whose clean runs vary. In the validation (`envi diagnose validate`, seeds 100-109, 220 trials of
the cases none, none_gaussian, noise, saturation, lag and run_variation), the check is significant
in 78 of 100 steered trials with the deterministic head. It is significant in none of the 10 with
the Gaussian head and in none of the 110 diffdrive trials. Among the 78 are 5 of the 10 steered
trials whose models were trained on noisy logs: their runs repeat themselves where the noisy real
runs never do (0 of 200).

So the diagnosis says where runs part this way. A goal that counts or times events (how often
the robot overshoots, for how long) then differs partly for this reason, not for a missing effect.

The test compares like with like: one simulated run per real log's initial window, so each side
has as many runs. A deterministic model's replicates of one window are one run repeated. The one-sided
Fisher exact test (:func:`scipy.stats.fisher_exact`) asks whether simulated runs settle more often
than real ones, over all controller versions pooled.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..system import Channel
from .gap import LEVEL
from .shrink import Group

#: The longest cycle looked for, in rows. The tail must hold it at least :data:`MIN_REPEATS` times.
MAX_PERIOD = 8
MIN_REPEATS = 4


def settled_period(states: np.ndarray, channels: Sequence[Channel], skip: int) -> int | None:
    """The shortest period (1..:data:`MAX_PERIOD` rows) with which the last half of the scored rows
    (after ``skip``) of one run's ``states`` (T, |s|) repeat, every state the same reading
    (:meth:`~envi_py.system.Channel.reads`). None when they do not repeat, or when the tail is too
    short to hold :data:`MIN_REPEATS` cycles."""
    scored = states[skip:]
    tail = scored[len(scored) - len(scored) // 2 :]
    for p in range(1, MAX_PERIOD + 1):
        if len(tail) < MIN_REPEATS * p:
            return None
        if all(c.reads(tail[p:, k], tail[:-p, k]).all() for k, c in enumerate(channels)):
            return p
    return None


def cycle_check(groups: Sequence[Group], channels: Sequence[Channel], skip: int) -> dict[str, Any]:
    """Do the simulated runs settle into an exact cycle more often than the real ones?

    ``groups`` are (version label, real logs, simulated logs), as
    :func:`~envi_py.diagnose.shrink.simulate_groups` gives them. The simulated logs come in runs per
    real log, one real log after another. Only each real log's first simulated run is counted."""
    versions = []
    for label, real, sims in groups:
        per_window = len(sims) // len(real)
        first = sims[::per_window][: len(real)]
        real_p = [settled_period(lg.states, channels, skip) for lg in real]
        sim_p = [settled_period(lg.states, channels, skip) for lg in first]
        versions.append(
            {
                "controller": label,
                "runs": len(real),
                "real_settled": sum(p is not None for p in real_p),
                "sim_settled": sum(p is not None for p in sim_p),
                "sim_periods": sorted({p for p in sim_p if p is not None}),
            }
        )
    n = sum(v["runs"] for v in versions)
    real_k = sum(v["real_settled"] for v in versions)
    sim_k = sum(v["sim_settled"] for v in versions)
    p = float(stats.fisher_exact([[sim_k, n - sim_k], [real_k, n - real_k]], alternative="greater").pvalue)
    return {
        "runs": n,
        "real_settled": real_k,
        "sim_settled": sim_k,
        "periods": sorted({q for v in versions for q in v["sim_periods"]}),
        "p": p,
        "significant": bool(p <= LEVEL),
        "versions": versions,
    }


def cycle_text(check: dict[str, Any] | None) -> str:
    """The verdict's sentence when simulated runs settle where real ones do not; empty otherwise."""
    if not check or not check["significant"]:
        return ""
    periods = " or ".join(str(q) for q in check["periods"])
    return (
        f"The model's runs settle into an exact repeating cycle (period {periods} rows) in "
        f"{check['sim_settled']} of {check['runs']} runs, against {check['real_settled']} of {check['runs']} "
        f"real runs (one simulated run per real log's initial window; Fisher exact p={check['p']:.2g}). "
        "There the model repeats itself where the real runs keep changing, by a slow drift or at random. A "
        "deterministic model whose readings are rounded to the sensor's resolution does so once the change "
        "it predicts over a cycle rounds away. So part of the gap in goals that count or time events is the "
        "model's own, not a missing effect. "
    )

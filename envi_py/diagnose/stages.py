"""Stage 1 of the diagnosis: is the model's class itself wrong for the world?

A deterministic model (one predicted next state, no spread) simulates every run from its initial
window alone, so its runs differ only as much as their initial windows do. When the real runs vary
from run to run far more than that (noise, a different grip every run), every candidate test sees
that randomness first and the diagnosis leads with "noise" whatever else is missing. So the class is
checked first, where the randomness shows and where it matters:

- one step: the real readings scatter from step to step by more than the window explains and the
  sensor's resolution allows, counted at a typical step (a lagging loop's few large errors are not
  randomness; the noise candidate's test, :func:`~.effects.test_noise`, p <=
  :data:`LEVEL` Bonferroni over the states, and at least :data:`~.effects.MIN_SHARE` of the
  prediction error between similar situations);
- the goals: per controller version and goal, the standard deviation of the simulated runs against
  that of the real runs; their median ratio below 1 (the simulated runs vary less). Started from
  different initial windows a deterministic model's runs do differ, so this alone says little with
  a dozen runs; it says how much the randomness matters.

A deterministic model is too certain for the world when both hold.

It is then refitted with the Gaussian head (mean and spread of the next state), on the same data with
the same seed and settings otherwise, and the rest of the diagnosis is of the refit: a candidate
effect is ranked by what it explains beyond the better-fitted model of the same class.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..logs import Log
from ..model import Checkpoint
from .effects import MIN_SHARE, Finding, test_noise
from .residuals import ResidualSet
from .shrink import retrain_with

LEVEL = 0.05


def spread_check(ckpt: Checkpoint, gaps: Sequence[dict[str, Any]], res: ResidualSet) -> dict[str, Any]:
    """The scatter of the real readings the model cannot predict, the simulated against the real
    run-to-run spread of every goal of every version, and whether a deterministic model is too
    certain for the world (see the module docstring)."""
    rows = []
    for g in gaps:
        for r in g["gaps"]:
            real, sim = np.asarray(r["real"], float), np.asarray(r["sim"], float)
            sd_real, sd_sim = float(np.std(real, ddof=1)), float(np.std(sim, ddof=1))
            if sd_real > 0:
                rows.append(
                    {
                        "controller": g["controller"],
                        "goal": r["goal"],
                        "unit": r["unit"],
                        "sd_real": sd_real,
                        "sd_sim": sd_sim,
                        "ratio": sd_sim / sd_real,
                    }
                )
    narrower = sum(r["ratio"] < 1 for r in rows)
    p = float(stats.binomtest(narrower, len(rows), 0.5, alternative="greater").pvalue) if rows else 1.0
    median = float(np.median([r["ratio"] for r in rows])) if rows else 1.0
    deterministic = ckpt.config.head != "gaussian"
    scatter = []
    for st in res.states:
        _, p_noise, share, detail = test_noise(st, ckpt)
        scatter.append(
            {
                "state": st.name,
                "p": min(1.0, p_noise * len(res.states)),
                "share": share,
                "detail": detail,
                "random": bool(p_noise * len(res.states) <= LEVEL and share >= MIN_SHARE),
            }
        )
    random_world = any(s["random"] for s in scatter)
    return {
        "head": ckpt.config.head,
        "scatter": scatter,
        "goals": rows,
        "median_ratio": median,
        "narrower": narrower,
        "tested": len(rows),
        "p": p,
        "too_certain": bool(deterministic and random_world and rows and median < 1.0),
    }


def refit_gaussian(ckpt: Checkpoint, train_logs: Sequence[Log], val_logs: Sequence[Log]) -> Checkpoint:
    """The same training as ``ckpt`` (data, seed, hyper-parameters, window), with the Gaussian head."""
    refit = Finding("model class", 0.0, 0.0, 0.0, "the real runs vary; the model does not", {"head": "gaussian"})
    return retrain_with(ckpt, refit, train_logs, val_logs)


def stage_text(check: dict[str, Any], before: float, after: float | None) -> str:
    """What the verdict says first when the model class is wrong."""
    scatter = "; ".join(s["detail"] for s in check["scatter"] if s["random"])
    text = (
        f"First, the model class: the model is deterministic, while the real runs vary: {scatter}. Its "
        f"simulated runs spread {check['median_ratio']:.0%} as widely as the real ones over the goals (median "
        f"of the standard deviations' ratio; narrower in {check['narrower']} of {check['tested']} goals, sign test "
        f"p={check['p']:.2g}). "
    )
    if after is None:
        return text + "Refit it with a Gaussian head (envi train --head gaussian) before diagnosing the rest. "
    return text + (
        f"Refitted with a Gaussian head (same data, seed and settings), the mean normalised W1 over the goals "
        f"goes from {before:.4f} to {after:.4f}; the rest of this diagnosis is of the refit. "
    )

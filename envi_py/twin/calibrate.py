"""Fit the twin's profile to real logs of several controller versions at once, and report the fit.

The loss is what the project verifies against: per controller version, the Wasserstein-1 distance
of each of the eight goal metrics and of six run statistics (oscillation period and amplitude, mean
and spread of the colour, the safety/comfort pair), each divided by its real-vs-real floor (same distance
between two random
halves of the real runs). A loss of 1 means "as close to reality as reality is to itself".
Sampling jitter and quantisation are estimated directly from the logs, not searched.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from scipy import stats

from envi_py.controllers import ControllerSpec
from envi_py.logs import Log, group_by_param
from envi_py.metrics import METRIC_NAMES, MetricConfig, driving_metrics, metric_bounds, safety_comfort

from .effects import resolve
from .generate import simulate
from .profile import TwinProfile

STAT_NAMES: tuple[str, ...] = ("period", "amplitude", "colour_mean", "colour_sd", "safety", "comfort")


def run_stats(color: np.ndarray, threshold: float = 40.0) -> np.ndarray:
    """Per run (R, T) -> (R, 6): oscillation period (ticks, from crossings of the threshold),
    amplitude (half the 5..95 percentile range), colour mean and sd, and the safety/comfort pair
    of :func:`envi_py.metrics.safety_comfort` (so their Gaussian KL divergence is fitted too)."""
    above = color > threshold
    crossings = (above[:, 1:] != above[:, :-1]).sum(1)
    period = 2 * (color.shape[1] - 1) / np.maximum(crossings, 1)
    lo, hi = np.percentile(color, [5, 95], axis=1)
    sc = safety_comfort(color, MetricConfig(centre=threshold, skip=0))
    return np.stack([period, (hi - lo) / 2, color.mean(1), color.std(1), sc[:, 0], sc[:, 1]], axis=1)


def features(color: np.ndarray, cfg: MetricConfig) -> np.ndarray:
    """The 14 per-run quantities compared: 8 goal metrics (scaled by their range) and 6 statistics."""
    lo, hi = metric_bounds(color.shape[1] - cfg.skip, cfg)
    return np.concatenate([driving_metrics(color, cfg) / (hi - lo), run_stats(color[:, cfg.skip :], cfg.centre)], 1)


FEATURE_NAMES = METRIC_NAMES + STAT_NAMES


def w1_all(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([stats.wasserstein_distance(a[:, j], b[:, j]) for j in range(a.shape[1])])


def w1_floor(feat: np.ndarray, splits: int = 20, seed: int = 0) -> np.ndarray:
    """Mean W1 between two random halves of the real runs, per feature (the real-vs-real floor)."""
    rng = np.random.default_rng(seed)
    n = feat.shape[0]
    out = []
    for _ in range(splits):
        perm = rng.permutation(n)
        out.append(w1_all(feat[perm[: n // 2]], feat[perm[n // 2 :]]))
    return np.mean(out, axis=0)


@dataclass
class Target:
    """Real runs of one controller version and their floor."""

    spec: ControllerSpec
    color: np.ndarray  # (R, T)
    feat: np.ndarray
    floor: np.ndarray


def targets(logs: list[Log], key: str, cfg: MetricConfig) -> list[Target]:
    """One target per controller version (value of ``key``) in the real logs."""
    out = []
    for value, group in group_by_param(logs, key).items():
        lens = {len(lg) for lg in group}
        steps = min(lens)
        color = np.stack([lg.states[:steps, cfg.channel] for lg in group])
        c = group[0].meta.controller or {"name": "lane-keeping", "params": {}}
        spec = ControllerSpec(c["name"], dict(c.get("params", {})))
        feat = features(color, cfg)
        out.append(Target(spec, color, feat, np.maximum(w1_floor(feat), 1e-6)))
    return out


def estimate_timing(logs: list[Log]) -> tuple[float, dict[str, float]]:
    """Nominal period and the jitter effect, straight from the logged time stamps.

    Period = the smallest regular step; extra delay ~ floor(Exponential(s)) with s chosen so the
    mean extra matches; pauses = steps longer than 1 s (the logs continue smoothly across them).
    """
    dt = np.concatenate([np.diff(lg.time) for lg in logs])
    pauses = dt > 1000
    regular = dt[~pauses]
    period = float(np.percentile(regular, 1))
    mean_extra = max(float(regular.mean() - period), 1e-3)
    scale = 1.0 / math.log1p(1.0 / mean_extra)  # E[floor(Exp(s))] = 1 / (e^(1/s) - 1)
    return period, {
        "extra_ms": round(scale, 4),
        "pause_prob": round(float(pauses.mean()), 6),
        "pause_ms": round(float(dt[pauses].mean()) if pauses.any() else 0.0, 1),
    }


# The searched parameters: (name, low, high, log-scale). Effect parameters are "effect.param".
SPACE: tuple[tuple[str, float, float, bool], ...] = (
    ("speed", 40.0, 400.0, True),
    ("spot", 3.0, 40.0, True),
    ("ahead", 0.0, 150.0, False),
    ("delay.ticks", 0.0, 2.99, False),
    ("rate_limit.deg_per_s", 150.0, 3000.0, True),
    ("noise.sigma", 0.0, 4.0, False),
    ("lowpass.tau_ms", 1.0, 60.0, True),
    ("black", 2.0, 10.0, False),
    ("white", 60.0, 85.0, False),
    ("gamma", 0.4, 2.5, True),
    ("run_variation.white_sd", 0.0, 8.0, False),
    ("run_variation.speed_sd", 0.0, 0.25, False),
    ("run_variation.grip_sd", 0.0, 0.25, False),
    ("steer_limit.pos_deg", 20.0, 90.0, False),
    ("steer_limit.neg_deg", 20.0, 90.0, False),
    ("curvature.mean_per_m", -6.0, 6.0, False),
    ("curvature.amp_per_m", 0.0, 4.0, False),
)


def _neutral(effect: str, lo: float, hi: float) -> float:
    """The searched value at which an effect does nothing: zero, or the fastest/widest steering."""
    return 0.0 if lo <= 0 <= hi else (hi if effect in ("rate_limit", "steer_limit") else lo)


def to_profile(u: np.ndarray, base: TwinProfile) -> TwinProfile:
    """Unit-cube point -> profile (delay ticks are floored to an integer)."""
    phys: dict[str, Any] = {}
    effects: dict[str, dict[str, float]] = {k: dict(v) for k, v in resolve(base.effects, None).items()}
    for (name, lo, hi, log), x in zip(SPACE, np.clip(u, 0, 1)):
        v = math.exp(math.log(lo) + x * (math.log(hi) - math.log(lo))) if log else lo + x * (hi - lo)
        if "." in name:
            eff, par = name.split(".")
            if eff == "delay":
                v = float(math.floor(v))
            effects.setdefault(eff, resolve({}, {eff: True})[eff])[par] = round(float(v), 5)
        else:
            phys[name] = round(float(v), 5)
    searched: dict[str, list[tuple[str, float]]] = {}
    for name, lo, hi, _ in SPACE:
        if "." in name:
            eff, par = name.split(".")
            searched.setdefault(eff, []).append((par, _neutral(eff, lo, hi)))
    effects = {
        k: v for k, v in effects.items() if k not in searched or any(v[p] != neutral for p, neutral in searched[k])
    }
    return base.replace(**phys, effects=effects)


def from_profile(profile: TwinProfile) -> np.ndarray:
    """Profile -> unit-cube point (inverse of :func:`to_profile`); an absent effect maps to its
    neutral value (zero, or the fastest and widest steering), so a search can start from any profile."""
    u = []
    for name, lo, hi, log in SPACE:
        if "." in name:
            eff, par = name.split(".")
            if eff in profile.effects:
                v = resolve({}, {eff: profile.effects[eff]})[eff][par]
            else:
                v = _neutral(eff, lo, hi)
            if eff == "delay":
                v += 0.5  # the middle of the interval that floors to this many ticks
        else:
            v = getattr(profile, name)
        v = min(max(v, lo), hi)
        u.append((math.log(v) - math.log(lo)) / (math.log(hi) - math.log(lo)) if log else (v - lo) / (hi - lo))
    return np.array(u)


def twin_color(profile: TwinProfile, spec: ControllerSpec, runs: int, steps: int, seed: int) -> np.ndarray:
    _, color, _ = simulate(spec, runs, steps, resolve(profile.effects, None), profile, np.random.default_rng(seed))
    return color


def ratios(profile: TwinProfile, tgts: list[Target], cfg: MetricConfig, runs: int, seed: int) -> np.ndarray:
    """(X, 14) twin-vs-real W1 over the real-vs-real floor, per target and feature."""
    out = []
    for i, t in enumerate(tgts):
        color = twin_color(profile, t.spec, runs, t.color.shape[1], seed + i)
        out.append(w1_all(t.feat, features(color, cfg)) / t.floor)
    return np.array(out)


def loss_of(r: np.ndarray) -> float:
    """Mean ratio, plus a share of the worst per version, so no version is sacrificed for the others."""
    return float(r.mean() + 0.25 * r.mean(axis=1).max())


def calibrate(
    logs: list[Log],
    key: str = "x",
    cfg: MetricConfig = MetricConfig(),
    budget_s: float = 420.0,
    runs: int = 160,
    seed: int = 0,
    base: TwinProfile | None = None,
    start: TwinProfile | None = None,
    progress: Callable[[str], None] | None = None,
) -> TwinProfile:
    """Random search then a shrinking (1+4) evolution strategy with restarts in the unit cube, common
    random numbers (fixed seed) so the loss is deterministic. Stops at ``budget_s`` seconds.
    ``start`` (e.g. the shipped profile) is the first candidate, so a refit never ends worse than it."""
    say = progress or (lambda s: None)
    period, jitter = estimate_timing(logs)
    effects = {"jitter": jitter, "quantise": {"step": 1.0}}
    base = (base or TwinProfile()).replace(period_ms=period, effects=effects)
    tgts = targets(logs, key, cfg)
    rng = np.random.default_rng(seed)
    t0 = _time.monotonic()
    best_u, best = None, math.inf
    n_random = 0
    if start is not None:
        best_u = from_profile(start)
        best = loss_of(ratios(to_profile(best_u, base), tgts, cfg, runs // 2, seed))
        say(f"start: loss {best:.3f}")
    while _time.monotonic() - t0 < budget_s * 0.3 or best_u is None:
        u = rng.random(len(SPACE))
        f = loss_of(ratios(to_profile(u, base), tgts, cfg, runs // 2, seed))
        n_random += 1
        if f < best:
            best_u, best = u, f
            say(f"random {n_random}: loss {best:.3f}")
    best = loss_of(ratios(to_profile(best_u, base), tgts, cfg, runs, seed))  # same runs as the search below
    step = 0.15
    evals = n_random
    while _time.monotonic() - t0 < budget_s:
        if step < 0.005:  # converged locally: restart the steps around the best point
            step = 0.1
        improved = False
        for _ in range(4):
            u = np.clip(best_u + step * rng.standard_normal(len(SPACE)), 0, 1)
            f = loss_of(ratios(to_profile(u, base), tgts, cfg, runs, seed))
            evals += 1
            if f < best:
                best_u, best, improved = u, f, True
        step = step * 1.3 if improved else step * 0.85
        if improved:
            say(f"es {evals}: loss {best:.3f} step {step:.3f}")
    prof = to_profile(best_u, base)
    say(f"done after {evals} evaluations, {_time.monotonic() - t0:.0f} s, loss {best:.3f}")
    return prof

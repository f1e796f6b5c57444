"""Candidate unmodelled effects: a statistical signature in the residuals and the model change that adds it.

Every test returns a p-value and a *share*: the fraction of the residual mean square the effect
accounts for. Residuals of one run are serially correlated (closed loop), so tests that treat
residuals as samples use an effective sample size ``n (1 - rho) / (1 + rho)`` from the lag-1
autocorrelation. P-values are Holm-corrected over all candidates; an effect is reported as
significant when its corrected p-value is below ``alpha`` *and* its share is at least
``min_share`` (with thousands of residuals, a real but negligible effect would otherwise be
flagged). Significant candidates are ranked by share.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
from scipy import stats

from ..model import Checkpoint, ModelConfig
from .residuals import Residuals


@dataclass(frozen=True)
class Finding:
    """The outcome of one candidate's test."""

    effect: str
    statistic: float
    p: float
    share: float
    detail: str
    fix: dict[str, Any]
    p_holm: float = float("nan")
    significant: bool = False

    def to_json(self) -> dict[str, Any]:
        return {"effect": self.effect, "statistic": self.statistic, "p": self.p, "p_holm": self.p_holm,
                "share": self.share, "significant": self.significant, "detail": self.detail,
                "fix": {k: list(v) if isinstance(v, tuple) else v for k, v in self.fix.items()}}


def _rho(res: Residuals) -> float:
    """Pooled lag-1 autocorrelation of residuals within runs."""
    same = res.run[1:] == res.run[:-1]
    a, b = res.r[:-1][same], res.r[1:][same]
    if len(a) < 3 or a.std() == 0 or b.std() == 0:
        return 0.0
    return float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, 0.95))


def n_eff(res: Residuals, n: int | None = None) -> float:
    rho = _rho(res)
    n = len(res) if n is None else n
    return max(10.0, n * (1 - rho) / (1 + rho))


def _ms(res: Residuals) -> float:
    return float(np.mean(res.r ** 2)) or 1e-12


def _ols_rss(y: np.ndarray, x: np.ndarray) -> float:
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    return float(np.sum((y - x @ coef) ** 2))


def test_memory(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Memory or delay beyond the window: do inputs *before* the window explain residuals that the
    window itself (linearly) does not? Only past inputs are used: in closed loop, future inputs are
    caused by the residual and prove nothing."""
    mask = ~np.isnan(res.beyond).any(axis=1)
    y = res.r[mask]
    if len(y) < 50:
        return 0.0, 1.0, 0.0, "too few windows with history before them"
    x0 = np.column_stack([np.ones(len(y)), res.window[mask]])
    x1 = np.column_stack([x0, res.beyond[mask]])
    rss0, rss1 = _ols_rss(y, x0), _ols_rss(y, x1)
    q = res.beyond.shape[1]
    dof = max(n_eff(res, len(y)) - x1.shape[1], 5)
    f = ((rss0 - rss1) / q) / (rss1 / dof)
    share = (rss0 - rss1) / float(np.sum(y ** 2))
    return float(f), float(stats.f.sf(f, q, dof)), float(share), \
        f"inputs up to {res.beyond.shape[1] // ckpt.config.channels} rows before the window explain " \
        f"{share:.1%} of the residual mean square"


def _unexplained(res: Residuals) -> tuple[np.ndarray, np.ndarray]:
    """Residuals minus their linear fit on every observable input (window and rows before it), with
    their run indices: what no input explains, so another effect's trace is not mistaken for noise."""
    mask = ~np.isnan(res.beyond).any(axis=1)
    if mask.sum() < 50:
        return res.r, res.run
    x = np.column_stack([np.ones(int(mask.sum())), res.window[mask], res.beyond[mask]])
    coef, *_ = np.linalg.lstsq(x, res.r[mask], rcond=None)
    return res.r[mask] - x @ coef, res.run[mask]


def test_noise(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Unmodelled noise: the white part of what no input explains (half the mean square of
    successive differences within a run) against the noise the model predicts (its Gaussian
    variance), or for a deterministic model against the resolution floor (a quantised sensor's
    step^2/12, and at least 0.5% of the state's range)."""
    u, run = _unexplained(res)
    same = run[1:] == run[:-1]
    white = float(np.mean(np.diff(u)[same] ** 2) / 2)
    if res.pred_std is not None:
        ref = float(np.mean(res.pred_std ** 2))
        what = "the model's predicted variance"
    else:
        span = float(np.ptp(res.real_next)) or 1.0
        step = 1.0 if np.all(np.abs(res.real_next - np.round(res.real_next)) < 1e-9) else 0.0
        ref = max(step ** 2 / 12, (0.005 * span) ** 2)
        what = "the resolution floor"
    ratio = white / max(ref, 1e-12)
    dof = n_eff(res)
    p = float(stats.chi2.sf(ratio * dof, dof))
    return ratio, p, min(1.0, white / _ms(res)), \
        f"white residual variance {white:.3g} is {ratio:.2f}x {what} ({ref:.3g})"


def test_quantisation(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Sensor quantisation: the real readings sit on an integer lattice but the model's do not."""
    if ckpt.config.round_to is not None:
        return 0.0, 1.0, 0.0, "the model already rounds its output"
    v = res.real_next
    on = np.abs(v - np.round(v)) < 1e-9
    k, n = int(on.sum()), len(v)
    p = float(stats.binom.sf(k - 1, n, 0.05)) if k else 1.0
    share = min(1.0, (1 / 12) / _ms(res)) if k == n else 0.0
    return k / n, p, share, f"{k / n:.1%} of real readings are integers; rounding error variance 1/12 is " \
                            f"{share:.1%} of the residual mean square"


def test_saturation(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Saturation at range limits: the model predicts beyond the range the real state ever reaches."""
    lo, hi = float(res.real_next.min()), float(res.real_next.max())
    margin = 0.01 * (hi - lo)
    out = (res.predicted > hi + margin) | (res.predicted < lo - margin)
    k, n = int(out.sum()), len(res)
    p = float(stats.binom.sf(k - 1, n, 0.01)) if k else 1.0
    share = float(np.sum(res.r[out] ** 2) / np.sum(res.r ** 2)) if k else 0.0
    return k / n, p, share, f"{k / n:.1%} of predictions leave the observed range [{lo:g}, {hi:g}]"


def test_drift(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Drift within a run: the per-run slope of residuals against time, tested across runs
    (one slope per run, so serial correlation within a run does not inflate the test)."""
    slopes, fitted = [], np.zeros_like(res.r)
    for run in np.unique(res.run):
        m = res.run == run
        t = res.row[m] - res.row[m].mean()
        if len(t) < 5 or np.all(t == 0):
            continue
        b = float(np.sum(t * res.r[m]) / np.sum(t * t))
        slopes.append(b)
    if len(slopes) < 3:
        return 0.0, 1.0, 0.0, "too few runs"
    slopes_a = np.array(slopes)
    tstat, p = stats.ttest_1samp(slopes_a, 0.0)
    for run in np.unique(res.run):
        m = res.run == run
        fitted[m] = slopes_a.mean() * (res.row[m] - res.row[m].mean())
    share = float(np.mean(fitted ** 2) / _ms(res))
    return float(tstat), float(p), share, f"residuals drift by {slopes_a.mean():+.3g} per row on average " \
                                          f"({len(slopes)} runs)"


def test_run_to_run(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Run-to-run variation: spread of per-run residual means against the spread expected from
    within-run variation, estimated by half-run differences (which share the serial correlation)."""
    means, halves = [], []
    for run in np.unique(res.run):
        r = res.r[res.run == run]
        if len(r) < 6:
            continue
        h = len(r) // 2
        means.append(r.mean())
        halves.append((r[:h].mean() - r[h:2 * h].mean()) / 2)
    if len(means) < 3:
        return 0.0, 1.0, 0.0, "too few runs"
    m, d = np.array(means), np.array(halves)
    f = float(np.var(m, ddof=1) / max(np.mean(d ** 2), 1e-12))
    p = float(stats.f.sf(f, len(m) - 1, len(d)))
    share = float(np.var(m) / _ms(res))
    return f, p, share, f"per-run residual means spread {np.std(m):.3g} vs {np.sqrt(np.mean(d ** 2)):.3g} " \
                        f"expected within runs ({len(m)} runs)"


def test_backlash(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Dead zone or backlash: just after the action reverses, residuals lean with (or against) the
    direction of the change, as the actuator first has to cross its gap."""
    recent = (res.since_change <= 3) & (res.change_dir != 0)
    y = res.r[recent] * res.change_dir[recent]
    if len(y) < 20:
        return 0.0, 1.0, 0.0, "too few action reversals"
    ne = max(5.0, n_eff(res, len(y)))
    tstat = float(y.mean() / (y.std(ddof=1) / np.sqrt(ne)))
    p = float(2 * stats.t.sf(abs(tstat), ne - 1))
    share = float(len(y) * y.mean() ** 2 / np.sum(res.r ** 2))
    return tstat, p, share, f"within 3 rows of an action change residuals lean {y.mean():+.3g} in the " \
                            f"change's direction ({len(y)} rows)"


def test_jitter(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Sampling jitter: a longer interval lets the state move further, so residuals follow the
    predicted change scaled by the interval's deviation from nominal."""
    period = ckpt.record.period_ms or float(np.median(res.dt))
    z = (res.dt / period - 1.0) * (res.predicted - res.state)
    if np.allclose(z, 0):
        return 0.0, 1.0, 0.0, "no interval variation"
    x = np.column_stack([np.ones(len(z)), z])
    rss0 = float(np.sum((res.r - res.r.mean()) ** 2))
    rss1 = _ols_rss(res.r, x)
    dof = max(n_eff(res) - 2, 5)
    f = (rss0 - rss1) / (rss1 / dof)
    share = (rss0 - rss1) / float(np.sum(res.r ** 2))
    return float(f), float(stats.f.sf(f, 1, dof)), float(share), \
        f"the interval's deviation explains {share:.1%} of the residual mean square " \
        f"(period sd {np.std(res.dt):.2g} ms)"


def _longer_history(cfg: ModelConfig) -> dict[str, Any]:
    return {"history": cfg.history * 2}


@dataclass(frozen=True)
class Candidate:
    """One effect of the library: its test and the change to the model config that adds it."""

    name: str
    what: str
    test: Callable[[Residuals, Checkpoint], tuple[float, float, float, str]]
    fix: Callable[[ModelConfig], dict[str, Any]]
    twin_effects: tuple[str, ...] = field(default=())  # twin effects this candidate stands for


CANDIDATES: tuple[Candidate, ...] = (
    Candidate("memory_delay", "missing memory or actuation delay", test_memory, _longer_history,
              ("delay", "lag", "lowpass")),
    Candidate("noise", "unmodelled noise", test_noise, lambda c: {"head": "gaussian"}, ("noise", "glitch")),
    Candidate("quantisation", "sensor quantisation", test_quantisation, lambda c: {"round_to": (1.0,) * c.n_state},
              ("quantise",)),
    Candidate("saturation", "saturation at range limits", test_saturation, lambda c: {}, ("saturation",)),
    Candidate("drift", "drift within a run", test_drift, lambda c: {"extras": tuple(c.extras) + ("phase",)},
              ("battery",)),
    Candidate("run_to_run", "run-to-run variation", test_run_to_run, lambda c: {"context": True},
              ("run_variation",)),
    Candidate("backlash", "dead zone or backlash", test_backlash, _longer_history, ("backlash", "deadzone")),
    Candidate("jitter", "sampling jitter", test_jitter, lambda c: {"extras": tuple(c.extras) + ("dt",)},
              ("jitter",)),
)


def holm(pvalues: Sequence[float]) -> np.ndarray:
    """Holm-Bonferroni adjusted p-values (monotone, capped at 1)."""
    p = np.asarray(pvalues, dtype=float)
    order = np.argsort(p)
    m = len(p)
    adj = np.empty(m)
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        adj[i] = running
    return adj


def run_candidates(res: Residuals, ckpt: Checkpoint, alpha: float = 0.05, min_share: float = 0.05,
                   candidates: Sequence[Candidate] = CANDIDATES) -> list[Finding]:
    """Every candidate's finding, significant ones first (by share), then the rest by p-value."""
    raw = []
    for c in candidates:
        stat, p, share, detail = c.test(res, ckpt)
        fix = c.fix(ckpt.config)
        if c.name == "saturation":
            fix = {"limits": ((float(res.real_next.min()), float(res.real_next.max())),)}
        raw.append(Finding(c.name, stat, p, share, detail, fix))
    adj = holm([f.p for f in raw])
    out = [Finding(f.effect, f.statistic, f.p, f.share, f.detail, f.fix, float(a),
                   bool(a < alpha and f.share >= min_share)) for f, a in zip(raw, adj)]
    return sorted(out, key=lambda f: (not f.significant, -f.share if f.significant else f.p_holm))

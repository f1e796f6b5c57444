"""Candidate unmodelled effects: a statistical signature in the residuals and the model change that adds it.

Most tests work on matched pairs (:class:`~.residuals.Pairs`): each residual against the one whose
window is nearest among the other runs. A model's misfit is a smooth function of its window and
cancels in the difference; an unmodelled effect does not, because it depends on something the
window does not hold (rows before it, time in the run, the interval, the run, noise). Every test
returns a p-value and a *share*: the fraction of the (differenced) residual mean square the effect
accounts for. Residuals of one run are serially correlated (closed loop), so the tests use an
effective sample size ``n (1 - rho) / (1 + rho)`` from the lag-1 autocorrelation. P-values are
Holm-corrected over all candidates; an effect is reported as
significant when its corrected p-value is below ``alpha`` *and* its share is at least
``min_share`` (with thousands of residuals, a real but negligible effect would otherwise be
flagged; :data:`MIN_SHARE`, or a candidate's own bar).

Every test looks at one state channel's residuals. A system with several states has each candidate
tried on each of them, and a candidate tied to one action (the play of an actuator) on each action;
the finding is then named with its channel ("noise on distance", "backlash on steering"). A system
of one state and one action (the lane-keeping robot) keeps the bare names.

Pairs see nothing of a misfit, which is most of the residual when the logs come from a world the
model was not trained on. For that case a candidate may also have a *what-if* (:mod:`.what_if`):
the model is fed its inputs as the effect would have changed them, and the part of the raw
residual mean square that removes is a second route to significance (:data:`WHAT_IF_BAR`).

When the diagnosed logs come from another world than the model's training logs (they fit
significantly and clearly worse than its own held-out logs, :func:`~.run.another_world`), the
model's own shortcomings show in them too: a model of too short a
window lacks memory on its training world as much as on any other. There a share counts only for
what it explains beyond the share the same test finds on the held-out logs (:attr:`Finding.excess`):
what changed between the worlds, not what the model always missed.

Significant candidates are ranked by the larger of their two shares, with one exception for nested
candidates (:data:`NESTED`): backlash is a particular memory, of the last reversal. Rows before the
window approximate any dependence on history, hysteresis included, so the memory test's share stays
high under backlash; only hysteresis makes the play filter explain something *beyond* those rows.
When memory leads by its pair test and the backlash test (conditioned on those rows) is
significant, backlash is named first and memory follows it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from ..logs import Log
from ..model import Checkpoint
from .residuals import PLAY_WIDTHS, Residuals, ResidualSet
from .what_if import WhatIf, actuator_lags, input_what_if


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
    what_if: float = 0.0  # part of the raw residual mean square its what-if removes (:mod:`.what_if`)
    candidate: str = ""  # the library candidate (:data:`CANDIDATES`); the effect's name when empty
    signal: str = ""  # the channel it is tied to (a state, or an action for an action's candidate)
    state: str = ""  # the state whose residuals show it
    # the share the same test finds on the model's own held-out logs, counted against ``share`` when
    # the diagnosed logs come from another world (:func:`run_candidates`); 0 otherwise
    held_out: float = 0.0

    def __post_init__(self) -> None:
        if not self.candidate:
            object.__setattr__(self, "candidate", self.effect)

    @property
    def excess(self) -> float:
        """The share beyond what the test finds on the model's own held-out logs."""
        return max(0.0, self.share - self.held_out)

    @property
    def weight(self) -> float:
        """What ranks significant findings: the larger of the share beyond the held-out logs and the what-if."""
        return max(self.excess, self.what_if)

    def to_json(self) -> dict[str, Any]:
        return {
            "effect": self.effect,
            "candidate": self.candidate,
            "signal": self.signal,
            "state": self.state,
            "statistic": self.statistic,
            "p": self.p,
            "p_holm": self.p_holm,
            "share": self.share,
            "held_out_share": self.held_out,
            "what_if": self.what_if,
            "significant": self.significant,
            "detail": self.detail,
            "fix": {k: list(v) if isinstance(v, tuple) else v for k, v in self.fix.items()},
        }


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


def _ols_rss(y: np.ndarray, x: np.ndarray) -> float:
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    return float(np.sum((y - x @ coef) ** 2))


def _fit_dof(y: np.ndarray, x: np.ndarray, run: np.ndarray) -> tuple[float, float, int]:
    """RSS of ``y`` on ``x``, the effective sample size from the lag-1 autocorrelation of the
    fitted residuals within runs (the alternative's residuals: an effect's own persistence must
    not be counted as serial correlation), and the rank of ``x``."""
    coef, _, rank, _ = np.linalg.lstsq(x, y, rcond=None)
    e = y - x @ coef
    same = run[1:] == run[:-1]
    a, b = e[:-1][same], e[1:][same]
    rho = float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, 0.95)) if len(a) > 2 and a.std() > 0 and b.std() > 0 else 0.0
    return float(np.sum(e**2)), max(10.0, len(y) * (1 - rho) / (1 + rho)), int(rank)


def _diff(res: Residuals, v: np.ndarray) -> np.ndarray:
    """``v_i - v_j`` over the matched pairs."""
    p = res.pairs
    return v[p.i] - v[p.j]


def _change(res: Residuals) -> np.ndarray:
    """The change of state the model predicts: anything that scales motion (speed, interval) scales it."""
    return res.predicted - res.state


def _null(res: Residuals) -> np.ndarray:
    """What a residual difference owes to the (small) difference of the two windows: the model's
    misfit to first order. Every test asks for more than this."""
    return np.column_stack([np.ones(len(res.pairs)), _diff(res, res.window)])


def _f_test(
    res: Residuals, x: np.ndarray, mask: np.ndarray | None = None, given: np.ndarray | None = None
) -> tuple[float, float, float]:
    """Do the pair differences ``x`` explain the residual differences (beyond the window's and
    ``given``'s)? F statistic, p-value and the share of the differenced mean square they explain
    (beyond what chance explains)."""
    y = _diff(res, res.r)
    if mask is not None:
        y, x = y[mask], x[mask]
    if len(y) < 30 or x.ndim == 1 and np.allclose(x, 0):
        return 0.0, 1.0, 0.0
    x = x.reshape(len(y), -1)
    x0 = _null(res) if given is None else np.column_stack([_null(res), given])
    x0 = x0 if mask is None else x0[mask]
    run = res.run[res.pairs.i] if mask is None else res.run[res.pairs.i][mask]
    return _compare(y, x0, np.column_stack([x0, x]), run)


def _compare(y: np.ndarray, x0: np.ndarray, x1: np.ndarray, run: np.ndarray) -> tuple[float, float, float]:
    """F test of the nested regressions ``x0`` within ``x1``, and the share of ``y``'s mean square
    the added columns explain beyond what as many columns of noise would."""
    rss0, _, rank0 = _fit_dof(y, x0, run)
    rss1, ne, rank1 = _fit_dof(y, x1, run)
    q = max(rank1 - rank0, 1)
    dof = max(ne - rank1, 5)
    f = ((rss0 - rss1) / q) / max(rss1 / dof, 1e-300)
    share = max(0.0, (rss0 - rss1) - q * rss1 / dof) / max(float(np.sum(y**2)), 1e-300)
    return float(f), float(stats.f.sf(f, q, dof)), float(share)


def misfit_share(res: Residuals) -> float:
    """The part of the one-step residual mean square that is a smooth function of the window (it
    cancels between look-alike windows): the model is wrong alike wherever the logs show similar windows.
    Large when the logs come from a world the training logs do not show; no added effect fixes
    that, training on such logs does."""
    p = res.pairs
    ms = float(np.mean(res.r[p.i] ** 2))
    return max(0.0, 1.0 - float(np.mean(_diff(res, res.r) ** 2)) / 2 / max(ms, 1e-300))


def lattice_step(v: np.ndarray) -> float | None:
    """The step of the lattice the readings sit on (``k * step + offset``), or None if they are
    continuous: far fewer distinct values than readings, all at multiples of the smallest gap."""
    u = np.unique(np.asarray(v, dtype=np.float64))
    if len(u) < 2 or len(u) > max(2, len(v) // 4):
        return None
    step = float(np.min(np.diff(u)))
    k = (u - u[0]) / step
    return step if np.all(np.abs(k - np.round(k)) < 1e-6) else None


def _beyond_mask(res: Residuals) -> np.ndarray:
    p = res.pairs
    return ~(np.isnan(res.beyond[p.i]).any(axis=1) | np.isnan(res.beyond[p.j]).any(axis=1))


def test_memory(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Memory or delay beyond the window: between windows that look alike, do the rows *before*
    the window explain the residuals (beyond what an actuator's play explains, which is memory of
    another kind: hysteresis)? Only past rows are used: in closed loop, later inputs are caused by
    the residual and prove nothing."""
    mask = _beyond_mask(res)
    x = np.nan_to_num(_diff(res, res.beyond))
    f, p, share = _f_test(res, x, mask, given=_diff(res, res.plays))
    rows = res.beyond.shape[1] // ckpt.config.channels
    period = ckpt.record.period_ms or float(np.median(res.dt))
    return (
        f,
        p,
        share,
        f"what happened {rows} rows ({rows * period:.0f} ms) before the model's window accounts for "
        f"{_pct(share)} of the prediction error of {res.name} between similar situations of different runs",
    )


def _pct(share: float) -> str:
    return f"{share:.1%}" if abs(share) < 0.1 else f"{share:.0%}"


def _in_units(value: float, res: Residuals) -> str:
    return f"{value:.3g} {res.unit}".rstrip()


def _features(res: Residuals, ckpt: Checkpoint) -> np.ndarray:
    """Every pair difference some candidate suspects, so noise is what none of them explains."""
    g = _change(res)
    cols = [
        np.nan_to_num(_diff(res, res.beyond)),
        _diff(res, res.row.astype(float)),
        _diff(res, res.row * g),
        _diff(res, _interval_change(res, ckpt)),
        _diff(res, res.plays),
    ]
    return np.column_stack(cols)


def typical_share(e: np.ndarray) -> float:
    """How much of the mean square of ``e`` a typical value carries: the robust (median absolute
    deviation) variance over the mean square, at most 1. About 1 for Gaussian scatter, about
    0.55 for t-distributed scatter of 3 degrees of freedom, and small when a few large jumps (a
    bump, a kick) carry most of it: the noise estimate of wavelet denoising, which keeps sparse
    features out of the noise level in the same way. Read off the diffdrive twin, whose periodic
    heading kick the mean square called noise in 40 of 40 verification trials."""
    ms = float(np.mean(e**2))
    if ms <= 0:
        return 1.0
    return min(1.0, float(stats.median_abs_deviation(e, scale="normal")) ** 2 / ms)


def test_noise(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Unmodelled noise: half the squared residual difference of look-alike windows, extrapolated to
    zero window distance (misfit grows with distance, noise does not) after removing what the other
    candidates explain, against the variance the model predicts (Gaussian head) or, for a
    deterministic model, the resolution floor (a lattice's step^2/12, at least (0.5% of range)^2).
    Noise is scatter at every step, so the estimate counts only what a typical step carries
    (:func:`typical_share`): a few large jumps, an occasional disturbance no candidate stands for,
    would otherwise read as a noise many times the real one, which a noise layer then spreads
    over every step."""
    p = res.pairs
    y = _diff(res, res.r)
    x = np.column_stack([_null(res), _features(res, ckpt), _run_effects(res)])
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    # the shape of the differences themselves: a least-squares fit of the other candidates' columns
    # smears a few large jumps over every residual
    h = typical_share(y) * (y - x @ coef) ** 2 / 2
    # Look-alike windows all at one distance (e.g. identical windows of a quantised sensor) leave
    # nothing to extrapolate from: then the mean is the estimate.
    a = np.column_stack([np.ones(len(h)), p.d2]) if np.ptp(p.d2) > 1e-12 else np.ones((len(h), 1))
    coef2, *_ = np.linalg.lstsq(a, h, rcond=None)
    white = float(coef2[0])
    dof = max(n_eff(res, len(h)) - a.shape[1], 5)
    se = float(np.sqrt(np.sum((h - a @ coef2) ** 2) / dof * np.linalg.pinv(a.T @ a)[0, 0]))
    if res.pred_std is not None:
        ref = float(np.mean((res.pred_std[p.i] ** 2 + res.pred_std[p.j] ** 2) / 2))
        what = "the scatter the model predicts"
    else:
        step = lattice_step(res.real_next) or 0.0
        span = float(np.ptp(res.real_next)) or 1.0
        ref = max(step**2 / 12, (0.005 * span) ** 2)
        what = "the model predicts none; the sensor's resolution alone gives"
    tstat = (white - ref) / max(se, 1e-300)
    share = max(0.0, 2 * (white - ref)) / max(float(np.mean(y**2)), 1e-300)
    sd, ref_sd = float(np.sqrt(max(white, 0.0))), float(np.sqrt(ref))
    return (
        white / max(ref, 1e-12),
        float(stats.t.sf(tstat, dof)),
        min(1.0, share),
        f"{res.name} scatters from step to step by sd {_in_units(sd, res)} that nothing in the window explains "
        f"({what} sd {_in_units(ref_sd, res)})",
    )


def test_quantisation(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Sensor quantisation: the real readings sit on a lattice but the model's predictions do not;
    rounding adds step^2/12 of variance the model cannot reproduce."""
    step = lattice_step(res.real_next)
    if step is None:
        return 0.0, 1.0, 0.0, f"the real {res.name} readings are continuous (no fixed step)"
    own = None if ckpt.config.round_to is None else ckpt.config.round_to[res.index]
    if own is not None and abs(own - step) <= 1e-6 * step:  # a finer or other step still predicts between
        return 0.0, 1.0, 0.0, f"the model already rounds its output (readings in steps of {_in_units(step, res)})"
    n = len(res.real_next)
    off = np.abs(res.predicted / step - np.round(res.predicted / step)) > 1e-6
    k = int(off.sum())
    p = float(stats.binom.sf(k - 1, n, 0.5)) if k else 1.0  # a lattice model would be off never
    share = min(1.0, 2 * (step**2 / 12) / max(float(np.mean(_diff(res, res.r) ** 2)), 1e-300))
    return (
        step,
        p,
        share,
        f"real {res.name} readings come in steps of {_in_units(step, res)} and the model predicts values "
        f"between them; rounding to that step accounts for {_pct(share)} of the prediction error between "
        "similar situations",
    )


def test_saturation(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Saturation at range limits: real readings pile up at their extreme value (at least 3x the
    mass of the adjacent bin, or of the busiest inner value when readings sit on a lattice;
    tested one-sided), which no smooth response produces. Its share is
    that of the residual differences of pairs with a reading at the limit (or a prediction beyond
    it, or a clipped reading in its window): there a reading says only that the state is somewhere
    past the limit."""
    v = res.real_next
    lo, hi = float(v.min()), float(v.max())
    step = lattice_step(v)
    if step is not None:  # every reading sits on a value: compare with the busiest inner value
        values, counts = np.unique(v, return_counts=True)
        inner = int(counts[1:-1].max()) if len(counts) > 2 else 0
        adjacent = [inner, inner]
    else:
        width = 0.02 * (hi - lo)
        adjacent = [int(np.sum((v < hi) & (v >= hi - width))), int(np.sum((v > lo) & (v <= lo + width)))]
    best = (0.0, 1.0, np.zeros(len(v), bool), "")
    for edge, adj in zip((hi, lo), adjacent):
        at = np.abs(v - edge) < 1e-9
        k, m = int(at.sum()), int(at.sum()) + adj
        p = float(stats.binom.sf(k - 1, m, 0.75)) if k > 1 else 1.0
        if p < best[1]:
            best = (k / max(1, m - k), p, at, f"{_pct(k / len(v))} of real {res.name} readings sit exactly at {edge:g}")
    ratio, p, at, detail = best
    if not at.any():
        return 0.0, 1.0, 0.0, f"no pile-up of {res.name} readings at the limits of their range"
    edge = float(v[at][0])
    cfg = ckpt.config
    k = res.index
    z = float((edge - ckpt.norm.low[k]) / ckpt.norm.half[k] - 1.0)  # the edge, normalised as the window is
    seen = np.abs(res.window[:, k :: cfg.row_width] - z) < 1e-5 * max(1.0, abs(z))  # this state, every row
    hit = at | seen.any(axis=1) | (res.predicted > hi) | (res.predicted < lo)
    pr = res.pairs
    y = _diff(res, res.r)
    share = float(np.sum(y[hit[pr.i] | hit[pr.j]] ** 2) / max(float(np.sum(y**2)), 1e-300))
    return (
        float(ratio),
        p,
        share,
        f"{detail}{' ' + res.unit if res.unit else ''}, {ratio:.1f}x as many as just inside it (a sensor that "
        f"clips); errors next to that limit are {_pct(share)} of the prediction error between similar situations",
    )


def test_drift(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Drift within a run: between look-alike windows at different times of their runs, do the
    residuals differ with time, as an offset or as a gain on the predicted change (a sagging
    battery slows every move)?"""
    t = res.row.astype(float)
    x = np.column_stack([_diff(res, t), _diff(res, t * _change(res))])
    f, p, share = _f_test(res, x)
    return (
        f,
        p,
        share,
        f"time since the start of the run accounts for {_pct(share)} of the prediction error of {res.name} "
        "between similar situations (a slow change within each run: a sagging battery, warming up)",
    )


def _run_effects(res: Residuals) -> np.ndarray:
    """Per-run offset and gain on the predicted change, for the first residual of each pair."""
    p = res.pairs
    g = _change(res)[p.i]
    runs, idx = np.unique(res.run[p.i], return_inverse=True)
    dummies = np.zeros((len(p), len(runs)))
    dummies[np.arange(len(p)), idx] = 1.0
    return np.column_stack([dummies, dummies * g[:, None]])


def test_run_to_run(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Run-to-run variation: residual differences against look-alike windows of other runs, grouped
    by run, differ between runs (in offset and in gain on the predicted change) more than chance."""
    p = res.pairs
    y = _diff(res, res.r)
    runs = np.unique(res.run[p.i])
    if len(runs) < 3:
        return 0.0, 1.0, 0.0, f"too few runs ({len(runs)}) to compare runs"
    x0 = np.column_stack([_null(res), _change(res)[p.i]])
    f, pv, share = _compare(y, x0, np.column_stack([x0, _run_effects(res)]), res.run[p.i])
    return (
        f,
        pv,
        share,
        f"an offset and a gain of its own for each of the {len(runs)} runs account for {_pct(share)} of the "
        f"prediction error of {res.name} between similar situations: the runs differ from each other",
    )


def _best_play(res: Residuals) -> tuple[float, float, float, int]:
    """F, p (uncorrected), share and index into :data:`PLAY_WIDTHS` of the play width that explains
    the most of the residual differences beyond the rows before the window (searched once per view)."""
    if "play" in res.memo:
        return res.memo["play"]
    best = (0.0, 1.0, 0.0, 0)
    for k in range(res.play.shape[1]):
        f, p, share = _f_test(
            res, _diff(res, res.play[:, k]), _beyond_mask(res), given=np.nan_to_num(_diff(res, res.beyond))
        )
        if share > best[2] or (best[2] == 0 and p < best[1]):
            best = (f, p, share, k)
    res.memo["play"] = best
    return best


def test_backlash(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Dead zone or backlash: between look-alike windows, residuals follow where an actuator with
    play would sit relative to the command (a hysteresis of the whole action history), beyond what
    the rows before the window explain linearly; the best of a few play widths (Bonferroni)."""
    f, p, share, k = _best_play(res)
    return (
        f,
        min(1.0, p * res.play.shape[1]),
        share,
        f"a play of {PLAY_WIDTHS[k]:.0%} of the {res.action_name} range in the actuator (a dead band the "
        f"command must cross after each reversal) accounts for {_pct(share)} of the prediction error of "
        f"{res.name} between similar situations",
    )


def _play_channel(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    """Backlash's fix: tell the model where the actuator sits in its play (the ``play`` channel,
    carried by the closed loop), at the width the test found. The model's play channel follows its
    first action only: play on another action has no model change to add (an empty fix)."""
    cfg = ckpt.config
    if res.action_index != 0:
        return {}
    extras = cfg.extras if "play" in cfg.extras else tuple(cfg.extras) + ("play",)
    return {"extras": extras, "play_width": PLAY_WIDTHS[_best_play(res)[3]]}


#: Intervals before the predicted one that the jitter test also reads. A sensor with a conversion
#: latency reads the surface one period late, so the motion of the previous interval is what its
#: next reading shows; an actuator whose response lags spreads one interval's motion over the next
#: ones. On the diffdrive twin (its sensor reads one period late, its motors lag about a period)
#: the three intervals explain 57-71 % of the differenced residuals, the predicted one alone 0.3 %.
JITTER_LAGS = 2


def _interval_change(res: Residuals, ckpt: Checkpoint) -> np.ndarray:
    """(N, 1 + JITTER_LAGS): the predicted change scaled by the deviation from nominal of the
    interval to the predicted row and of the :data:`JITTER_LAGS` intervals before it (0 where an
    earlier interval lies before the log's first residual or across a break in its rows)."""
    period = ckpt.record.period_ms or float(np.median(res.dt))
    cols = [res.dt / period - 1.0]
    fresh = np.concatenate([[True], (res.run[1:] != res.run[:-1]) | (res.row[1:] != res.row[:-1] + 1)])
    for _ in range(JITTER_LAGS):
        prev = np.concatenate([[0.0], cols[-1][:-1]])
        prev[fresh] = 0.0
        cols.append(prev)
    return np.column_stack(cols) * _change(res)[:, None]


def test_jitter(res: Residuals, ckpt: Checkpoint) -> tuple[float, float, float, str]:
    """Sampling jitter: a longer interval lets the state move further, so between look-alike windows
    residuals follow the predicted change scaled by the interval's deviation from nominal: of the
    interval to the predicted row and of the :data:`JITTER_LAGS` before it (one F test of all)."""
    z = _interval_change(res, ckpt)
    if np.allclose(z, 0):
        return 0.0, 1.0, 0.0, "the sampling interval never varies"
    f, p, share = _f_test(res, _diff(res, z))
    return (
        f,
        p,
        share,
        f"the sampling interval is {np.median(res.dt):.0f} ms (median; middle 90% "
        f"{np.percentile(res.dt, 5):.0f}-{np.percentile(res.dt, 95):.0f} ms, longest {np.max(res.dt):.0f} ms); "
        f"its variation accounts for {_pct(share)} of the prediction error of {res.name} between similar "
        "situations",
    )


def _gaussian_head(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    """Noise's fix: a Gaussian head; none for a model that has one (retraining it changes nothing)."""
    return {} if ckpt.config.head == "gaussian" else {"head": "gaussian"}


def _run_context(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    """Run-to-run variation's fix: sigma_0's context as an input; none for a model that reads it."""
    return {} if ckpt.config.context else {"context": True}


def _longer_history(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    return {"history": ckpt.config.history * 2}


def _round_states(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    """Quantisation's fix: round this state to the lattice its readings sit on; every other state
    keeps the model's rounding, else its declared resolution. Without either for some state the
    model cannot round one state alone (an empty fix)."""
    cfg = ckpt.config
    current = cfg.round_to or tuple(c.resolution for c in ckpt.schema.states)
    steps = tuple(lattice_step(res.real_next) or 1.0 if i == res.index else current[i] for i in range(cfg.n_state))
    return {"round_to": steps} if all(v is not None for v in steps) else {}


def _clip_and_remember(ckpt: Checkpoint, res: Residuals) -> dict[str, Any]:
    """Saturation's fix: clamp to the range the real readings reach, and give the model the rows to
    infer what a clipped reading hides (how far past the limit the state is, from how long the
    reading has sat there). Clamping alone changes nothing when the model already clamps to its
    training range; with the longer history the validation's saturation gap shrank by a median
    18% on 8 fresh seeds (6 of 8 better)."""
    low, high = ckpt.limits()
    limits = tuple(
        (float(res.real_next.min()), float(res.real_next.max())) if i == res.index else (float(lo), float(hi))
        for i, (lo, hi) in enumerate(zip(low, high))
    )
    return {"limits": limits, **_longer_history(ckpt, res)}


@dataclass(frozen=True)
class Candidate:
    """One effect of the library: its test and the change to the model config that adds it."""

    name: str
    what: str
    test: Callable[[Residuals, Checkpoint], tuple[float, float, float, str]]
    fix: Callable[[Checkpoint, Residuals], dict[str, Any]]  # {} when the model cannot express it
    twin_effects: tuple[str, ...] = field(default=())  # twin effects this candidate stands for
    min_share: float | None = None  # its own share bar instead of the common one (:data:`MIN_SHARE`)
    # its what-if (:mod:`.what_if`): one outcome per state channel
    what_if: Callable[[Checkpoint, Sequence[Log], ResidualSet], list[WhatIf]] | None = None
    per_action: bool = False  # tied to one action (tried on each), else to one state
    no_fix: str = "envi has no model change that adds it on this channel"  # why ``fix`` gave nothing

    def bar(self, common: float) -> float:
        """The share a significant finding of this candidate must reach."""
        return common if self.min_share is None else self.min_share


CANDIDATES: tuple[Candidate, ...] = (
    Candidate(
        "memory_delay",
        "missing memory or actuation delay",
        test_memory,
        _longer_history,
        ("delay", "lag", "lowpass"),
        what_if=lambda ckpt, logs, res: input_what_if(ckpt, logs, res, actuator_lags(res.actions)),
    ),
    Candidate(
        "noise",
        "unmodelled noise",
        test_noise,
        _gaussian_head,
        ("noise", "glitch"),
        no_fix="the model already predicts a spread (Gaussian head): retraining with one changes nothing",
    ),
    Candidate("quantisation", "sensor quantisation", test_quantisation, _round_states, ("quantise",)),
    Candidate("saturation", "saturation at range limits", test_saturation, _clip_and_remember, ("saturation",)),
    # Per-run offsets and trends in time absorb slow transients of a closed loop whose state the
    # window does not fully hold (PID steering of a clean twin: shares up to 5.5% on negative
    # controls), so these two need a higher bar; injected drift or run variation explains >= 14%.
    Candidate(
        "drift",
        "drift within a run",
        test_drift,
        lambda c, r: {"extras": tuple(c.config.extras) + ("phase",)},
        ("battery",),
        min_share=0.10,
    ),
    Candidate(
        "run_to_run",
        "run-to-run variation",
        test_run_to_run,
        _run_context,
        ("run_variation",),
        min_share=0.10,
        no_fix="the model already reads each run's start (run context): retraining with it changes nothing",
    ),
    # The play test is conditioned on the rows before the window, so a closed loop's slow transients
    # do not reach it: in 160 negative-control trials (seeds 0-79, both modes, bang-bang and PID
    # steering) it was never Holm-significant. It has no share bar: play acts only at reversals, so its
    # share stays small when its closed-loop gap is not (injected backlash on diffdrive, seeds
    # 100-119: 0.3-2.2% with gaps of 9-49x the floor; a 1% bar hid 9 of 20), and the closed-loop gap
    # test is the guard against a negligible effect. That guard is needed: under PID the clean
    # diffdrive robot's own motor dead zone makes the test significant in 10 of 25 negative controls
    # (seeds 80-84, 100-119), each with no significant gap. Chosen on diffdrive's figures, which is
    # said where they are reported; on steered (seeds 80-84, 100-119) it names 3 more backlash trials
    # and no false alarm.
    Candidate(
        "backlash",
        "dead zone or backlash",
        test_backlash,
        _play_channel,
        ("backlash", "deadzone"),
        min_share=0.0,
        per_action=True,
    ),
    Candidate(
        "jitter", "sampling jitter", test_jitter, lambda c, r: {"extras": tuple(c.config.extras) + ("dt",)}, ("jitter",)
    ),
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


#: The smallest share of the differenced residual mean square a significant effect must explain.
#: With thousands of residuals a real but negligible effect would otherwise be flagged. On 80
#: negative-control trials of ``envi diagnose validate`` under bang-bang steering (seeds 0-39, both
#: modes) the largest share a Holm-significant candidate reached was 2.0%; 3% keeps a margin above
#: that. A few candidates have their own bar (:attr:`Candidate.min_share`).
MIN_SHARE = 0.03


#: The part of the raw residual mean square a what-if must remove to count. On the validation's
#: negative controls and withheld-effect cases (seeds 0-4) the actuator-lag what-ifs removed at
#: most 15% (PID steering, p > 0.5) and usually made the fit far worse; an actuator lag the model
#: was not trained on: 97-98%.
WHAT_IF_BAR = 0.25


def _tried(c: Candidate, res: ResidualSet) -> list[tuple[str, list[Residuals]]]:
    """Where candidate ``c`` is tried: (channel, the views it is tested on) for each state, or for
    each action (tested on every state's residuals seen against that action)."""
    if c.per_action:
        return [(a, [res.view(k, j) for k in range(len(res.states))]) for j, a in enumerate(res.actions)]
    return [(s.name, [s]) for s in res.states]


def _named(c: Candidate, channel: str, res: ResidualSet) -> str:
    """The candidate's name, with its channel when the system has more than one of that kind."""
    several = len(res.actions) > 1 if c.per_action else len(res.states) > 1
    return f"{c.name} on {channel}" if several else c.name


def _test_views(
    c: Candidate, views: Sequence[Residuals], ckpt: Checkpoint
) -> tuple[Residuals, tuple[float, float, float, str]]:
    """The view (state) where the candidate explains the most, its p-value Bonferroni over the views."""
    outcomes = [(v, c.test(v, ckpt)) for v in views]
    view, (stat, p, share, detail) = max(outcomes, key=lambda o: (o[1][2], -o[1][1]))
    if len(views) > 1:
        detail = f"in {view.name}: {detail}"
    return view, (stat, min(1.0, p * len(views)), share, detail)


def run_candidates(
    res: ResidualSet,
    ckpt: Checkpoint,
    alpha: float = 0.05,
    min_share: float = MIN_SHARE,
    candidates: Sequence[Candidate] = CANDIDATES,
    logs: Sequence[Log] | None = None,
    held_out: Mapping[str, float] | None = None,
) -> list[Finding]:
    """Every candidate's finding on every channel it is tied to, significant ones first (by weight),
    then the rest by p-value.

    With the ``logs`` the residuals came from, candidates that have a what-if also try it; such a
    candidate has two routes to significance (its pair test's share, or its what-if's), and its
    p-value is the smaller of the two, doubled (Bonferroni). ``held_out`` (by finding name) holds
    the shares the same tests find on the model's own held-out logs: a share counts for what it
    explains beyond that (:attr:`Finding.excess`), in the bar and in the ranking."""
    raw, bars = [], []
    for c in candidates:
        ws = c.what_if(ckpt, logs, res) if c.what_if is not None and logs is not None else None
        for channel, views in _tried(c, res):
            view, (stat, p, share, detail) = _test_views(c, views, ckpt)
            fix = c.fix(ckpt, view)
            w = ws[view.index] if ws is not None else None
            if w is not None:
                p = min(1.0, 2 * min(p, w.p))
                detail += (
                    f"; feeding the model the commands through {w.label} removes {_pct(w.share)} of its one-step error"
                    if w.share > 0
                    else f"; what-if: {w.label}"
                )
            if not fix:
                detail += f"; {c.no_fix}"
            name = _named(c, channel, res)
            what_if = max(0.0, w.share) if w else 0.0
            own = (held_out or {}).get(name, 0.0)
            if own > 0:
                detail += f"; {_pct(own)} on the model's own held-out logs"
            raw.append(
                Finding(
                    name,
                    stat,
                    p,
                    share,
                    detail,
                    fix,
                    what_if=what_if,
                    candidate=c.name,
                    signal=channel,
                    state=view.name,
                    held_out=own,
                )
            )
            bars.append(c.bar(min_share))
    adj = holm([f.p for f in raw])
    out = [
        replace(f, p_holm=float(a), significant=bool(a < alpha and (f.excess >= bar or f.what_if >= WHAT_IF_BAR)))
        for f, a, bar in zip(raw, adj, bars)
    ]
    out.sort(key=lambda f: (not f.significant, -f.weight if f.significant else f.p_holm))
    return _nested_first(out, alpha)


#: Specific effect -> the general one its test is conditioned on (see the module docstring).
NESTED = {"backlash": "memory_delay"}


def _nested_first(findings: list[Finding], alpha: float) -> list[Finding]:
    """When the leading finding is a general effect and a specific form of it is significant beyond
    it, the specific one leads: it says what the general test only approximates. Not when the
    general one leads by its what-if: that names the form of the memory already (a lagging actuator)."""
    if not findings or not findings[0].significant or findings[0].what_if > findings[0].excess:
        return findings
    lead = findings[0]
    for specific, general in NESTED.items():
        if lead.candidate != general:
            continue
        s = next(
            (
                f
                for f in findings
                if f.candidate == specific and (not f.state or not lead.state or f.state == lead.state)
            ),
            None,
        )
        if s is not None and s.p_holm < alpha:
            named = replace(s, significant=True)
            return [named] + [f for f in findings if f is not s]
    return findings

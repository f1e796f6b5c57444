"""The numbers behind the engineer's plots, without matplotlib: MATLAB-style fit and residual correlations.

``fit_percent`` is the figure of MATLAB's ``compare`` (normalised root-mean-square fit, 100 = the
simulated trace equals the real one, 0 = no better than the real trace's mean, negative = worse).
``residual_correlations`` gives what MATLAB's ``resid`` plots: the residual's auto-correlation and its
cross-correlation with an input, with the 99 % band of a white residual independent of the input
(+-2.58/sqrt(N)); a model that captured the dynamics leaves residuals inside both bands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

#: Two-sided 99 % quantile of the standard normal: the band of ``resid``.
Z99 = 2.58


def fit_percent(y: np.ndarray, yhat: np.ndarray) -> float:
    """100 * (1 - ||y - yhat|| / ||y - mean(y)||) over one channel; NaN when ``y`` is constant
    (no variation to explain) or the arrays hold non-finite values."""
    y, yhat = np.asarray(y, dtype=float), np.asarray(yhat, dtype=float)
    if y.shape != yhat.shape or y.ndim != 1:
        raise ValueError(f"fit_percent needs two 1-D arrays of equal length, got {y.shape} and {yhat.shape}")
    if not (np.isfinite(y).all() and np.isfinite(yhat).all()):
        return float("nan")
    spread = float(np.linalg.norm(y - y.mean()))
    if spread == 0.0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / spread))


@dataclass(frozen=True)
class Correlations:
    """One residual channel against one input: auto-correlation at lags 0..M, cross-correlation at
    lags -M..M (positive lag: the input leads the residual), and the 99 % band."""

    lags: np.ndarray  # 0..M
    auto: np.ndarray  # (M+1,), auto[0] == 1
    cross_lags: np.ndarray  # -M..M
    cross: np.ndarray  # (2M+1,)
    band: float  # 2.58 / sqrt(N)
    n: int

    @property
    def auto_outside(self) -> int:
        """Lags 1..M whose auto-correlation leaves the band (lag 0 is 1 by definition)."""
        return int(np.sum(np.abs(self.auto[1:]) > self.band))

    @property
    def cross_outside(self) -> int:
        return int(np.sum(np.abs(self.cross) > self.band))


def residual_correlations(residual: np.ndarray, inp: np.ndarray, max_lag: int = 25) -> Correlations:
    """``resid``'s two correlation curves for one residual channel and one input signal (both (N,),
    same rows). Means are removed; both curves are normalised (biased estimate, as ``resid``)."""
    e, u = np.asarray(residual, dtype=float), np.asarray(inp, dtype=float)
    if e.ndim != 1 or u.shape != e.shape:
        raise ValueError(f"residual and input must be 1-D of equal length, got {e.shape} and {u.shape}")
    if not (np.isfinite(e).all() and np.isfinite(u).all()):
        raise ValueError("residual or input holds NaN or infinite values")
    n = e.shape[0]
    if n < 2 or max_lag < 1:
        raise ValueError(f"need at least 2 samples and max_lag >= 1, got {n} samples and max_lag {max_lag}")
    m = min(max_lag, n - 1)
    e, u = e - e.mean(), u - u.mean()
    ee, uu = float(e @ e), float(u @ u)
    if ee == 0.0:
        raise ValueError("the residual is constant: no correlation to show")
    full_auto = signal.correlate(e, e, mode="full")  # index n-1 is lag 0
    auto = full_auto[n - 1 : n + m] / ee
    full_cross = signal.correlate(e, u, mode="full")  # index n-1+k: sum_t e(t+k) u(t)
    cross = full_cross[n - 1 - m : n + m] / np.sqrt(ee * uu) if uu > 0 else np.zeros(2 * m + 1)
    return Correlations(np.arange(m + 1), auto, np.arange(-m, m + 1), cross, Z99 / np.sqrt(n), n)

"""A goal metric over runs: its mean with an interval and its quantiles with exact distribution-free intervals.

Mean: Student t interval by default (exact for normal metrics, close for moderate n otherwise), or a
BCa bootstrap (``scipy.stats.bootstrap``) for skewed metrics with enough runs (say 20+; with fewer the
bootstrap under-covers). Quantiles: the order-statistic interval [X_(l), X_(u)], which covers the true
q-quantile of ANY continuous distribution with probability binom.cdf(u-1, n, q) - binom.cdf(l-1, n, q)
(the number of runs below the quantile is Binomial(n, q)). l and u are chosen so each tail is at most
alpha/2; the achieved coverage is reported. With too few runs a side has no order statistic far enough
out and that bound is infinite: the honest statement that n runs cannot bound that quantile.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from ._checks import count, finite_vector, probability


@dataclass(frozen=True)
class MeanSummary:
    """The mean of a metric over n runs with its interval."""

    n: int
    mean: float
    sd: float
    low: float
    high: float
    confidence: float
    method: str  # "t" or "bca"

    def to_json(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "mean": self.mean,
            "sd": self.sd,
            "interval": [self.low, self.high],
            "confidence": self.confidence,
            "method": self.method,
        }


@dataclass(frozen=True)
class QuantileSummary:
    """One quantile's estimate and its order-statistic interval (ranks 1-based; 0 / n+1 mean unbounded)."""

    q: float
    n: int
    estimate: float
    low: float
    high: float
    rank_low: int
    rank_high: int
    coverage: float  # exact coverage probability of [X_(rank_low), X_(rank_high)] for continuous metrics

    def to_json(self) -> dict[str, Any]:
        return {
            "q": self.q,
            "n": self.n,
            "estimate": self.estimate,
            "interval": [_json_float(self.low), _json_float(self.high)],
            "ranks": [self.rank_low, self.rank_high],
            "coverage": self.coverage,
        }


def _json_float(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


def mean_interval(
    values: object, confidence: float = 0.95, method: str = "t", n_resamples: int = 9999, seed: int = 0
) -> MeanSummary:
    """The mean of ``values`` (one per run) with a two-sided ``confidence`` interval by ``method`` "t" or "bca".

    Runs with identical values give the zero-width interval at that value (no spread was observed;
    the report's n says how little that may mean).
    """
    x = finite_vector("values", values, 2)
    confidence = probability("confidence", confidence)
    if method not in ("t", "bca"):
        raise ValueError(f"method must be 't' or 'bca', got {method!r}")
    mean, sd = float(x.mean()), float(x.std(ddof=1))
    if sd == 0.0:
        return MeanSummary(x.size, mean, 0.0, mean, mean, confidence, method)
    if method == "t":
        lo, hi = stats.ttest_1samp(x, 0.0).confidence_interval(confidence)
    else:
        res = stats.bootstrap(
            (x,),
            np.mean,
            confidence_level=confidence,
            method="BCa",
            n_resamples=n_resamples,
            random_state=np.random.default_rng(seed),
        )
        lo, hi = res.confidence_interval
    return MeanSummary(x.size, mean, sd, float(lo), float(hi), confidence, method)


def order_statistic_ranks(n: int, q: float, confidence: float = 0.95) -> tuple[int, int, float]:
    """Ranks (l, u), 1-based, with P(X_(l) <= xi_q <= X_(u)) >= ``confidence`` and each tail <= alpha/2.

    l = 0 (or u = n + 1) when no order statistic bounds that side; the coverage returned is exact for a
    continuous distribution.
    """
    n = count("n", n, 1)
    q = probability("q", q)
    alpha = 1.0 - probability("confidence", confidence)
    ranks = np.arange(0, n + 1)
    below = stats.binom.cdf(ranks, n, q)  # below[j] = P(at most j runs lie below xi_q)
    # X_(l) <= xi_q fails iff at most l-1 runs lie below xi_q: that tail must be <= alpha/2
    lows = ranks[1:][below[:-1] <= alpha / 2]
    low = int(lows.max()) if lows.size else 0
    # X_(u) >= xi_q fails iff at least u runs lie below xi_q: P = 1 - below[u-1] <= alpha/2
    highs = ranks[1:][1.0 - below[:-1] <= alpha / 2]
    high = int(highs.min()) if highs.size else n + 1
    cover_low = below[low - 1] if low >= 1 else 0.0
    cover_high = below[high - 1] if high <= n else 1.0
    return low, high, float(cover_high - cover_low)


def quantile_interval(values: object, q: float, confidence: float = 0.95) -> QuantileSummary:
    """The ``q``-quantile of ``values`` with its exact distribution-free order-statistic interval."""
    x = np.sort(finite_vector("values", values, 1))
    lo_rank, hi_rank, cover = order_statistic_ranks(x.size, q, confidence)
    low = float(x[lo_rank - 1]) if lo_rank >= 1 else -np.inf
    high = float(x[hi_rank - 1]) if hi_rank <= x.size else np.inf
    return QuantileSummary(float(q), x.size, float(np.quantile(x, q)), low, high, lo_rank, hi_rank, cover)


@dataclass(frozen=True)
class MetricSummary:
    """A metric's mean and quantiles over the same n runs."""

    name: str
    n: int
    mean: MeanSummary
    quantiles: tuple[QuantileSummary, ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "n": self.n,
            "mean": self.mean.to_json(),
            "quantiles": [s.to_json() for s in self.quantiles],
        }


def summarise(
    name: str,
    values: object,
    quantiles: Sequence[float] = (0.05, 0.5, 0.95),
    confidence: float = 0.95,
    method: str = "t",
) -> MetricSummary:
    """Mean and quantiles of one metric, every interval at ``confidence``."""
    x = finite_vector(f"{name} values", values, 2)
    return MetricSummary(
        name,
        x.size,
        mean_interval(x, confidence, method),
        tuple(quantile_interval(x, q, confidence) for q in quantiles),
    )

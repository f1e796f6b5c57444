"""Sequential goal verdicts: simulate a batch, update, stop as soon as the answer is known.

Two procedures, both driven by ``sample(n) -> bool array`` (the caller simulates n runs):

* :func:`sprt`: Wald's sequential probability ratio test of p <= p_required - delta (FAIL) against
  p >= p_required + delta (PASS). Inside the indifference region (p_required +- delta) either verdict
  is acceptable; outside it a wrong verdict has probability about alpha (false PASS) or beta (false
  FAIL). Wald's thresholds ignore the overshoot at the stopping look, so the realised error rates are
  at or below the nominal ones (more so with large batches). It needs on average far fewer runs than
  the fixed-size test with the same error rates (:func:`fixed_sample_size`).
* :func:`confidence_sequence`: an interval for p valid at every look simultaneously, so it keeps its
  coverage at a data-dependent stopping time (a Clopper-Pearson interval recomputed after each batch
  does not: looking repeatedly inflates its error). Default: the beta-binomial mixture (Robbins)
  sequence {p : M_n(p) < 1/alpha}, M_n(p) = B(a+k, b+n-k) / B(a, b) / (p^k (1-p)^(n-k)), a
  nonnegative martingale under p, so by Ville's inequality it misses p at any time with probability
  <= alpha, however many looks. Alternative: ``method="bonferroni"``, Clopper-Pearson at alpha / L at
  each of the L = ceil(max_runs / batch) possible looks (alpha spent evenly over the looks). The running
  intersection of the intervals is reported (still valid: all hold at once). The verdict is PASS once
  the lower bound reaches p_required, FAIL once the upper bound drops below it.

The SPRT result carries the mixture interval computed on the same runs, so it too has an interval
that is valid at its stopping time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from ._checks import count, outcomes, probability
from .binomial import Verdict, clopper_pearson, verdict_of

Sampler = Callable[[int], np.ndarray]


@dataclass(frozen=True)
class Look:
    """The state after one batch: runs and successes so far, and the interval or the SPRT statistic."""

    runs: int
    successes: int
    low: float | None = None  # confidence-sequence looks: the running interval; SPRT looks: None
    high: float | None = None
    llr: float | None = None  # SPRT looks: log-likelihood ratio of p1 vs p0; confidence-sequence looks: None

    def to_json(self) -> dict[str, Any]:
        return {"runs": self.runs, "successes": self.successes, "interval": [self.low, self.high], "llr": self.llr}


@dataclass
class SequentialResult:
    """What a sequential procedure decided, after how many runs, with an interval valid at that time."""

    verdict: Verdict
    runs: int
    successes: int
    low: float
    high: float
    confidence: float  # of the (any-time valid) interval
    method: str
    max_runs: int
    batch: int
    looks: list[Look] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict.value,
            "runs": self.runs,
            "successes": self.successes,
            "interval": [self.low, self.high],
            "confidence": self.confidence,
            "method": self.method,
            "max_runs": self.max_runs,
            "batch": self.batch,
            "looks": [lk.to_json() for lk in self.looks],
        }


def _draw(sample: Sampler, n: int) -> np.ndarray:
    got = outcomes("sample(n) result", sample(n))
    if got.size != n:
        raise ValueError(f"sample({n}) returned {got.size} outcomes, expected {n}")
    return got


def _betaln(a: float, b: float) -> float:
    """log B(a, b) with the math module: scalar root finding calls it often and scipy's ufuncs cost ~10x more."""
    return math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)


def mixture_interval(k: int, n: int, confidence: float = 0.95, a: float = 0.5, b: float = 0.5) -> tuple[float, float]:
    """The beta-binomial mixture confidence-sequence interval at ``k`` successes of ``n`` runs.

    {p : log M_n(p) < log(1/alpha)}; -log L(p) is convex in p with its minimum at k/n, where M_n <= 1,
    so the set is an interval around k/n whose ends are found by root finding.
    """
    if n == 0:
        return 0.0, 1.0
    log_threshold = -math.log(1.0 - confidence)
    const = _betaln(a + k, b + n - k) - _betaln(a, b) - log_threshold

    def excess(p: float) -> float:  # log M_n(p) - log(1/alpha): negative inside the interval
        return const - (k * math.log(p) if k else 0.0) - ((n - k) * math.log1p(-p) if n > k else 0.0)

    p_hat, tiny = k / n, 1e-15
    lo = 0.0 if k == 0 or excess(tiny) < 0 else optimize.brentq(excess, tiny, p_hat, xtol=1e-12)
    hi = 1.0 if k == n or excess(1 - tiny) < 0 else optimize.brentq(excess, p_hat, 1 - tiny, xtol=1e-12)
    return float(lo), float(hi)


def _interval(method: str, k: int, n: int, confidence: float, looks_possible: int) -> tuple[float, float]:
    if method == "mixture":
        return mixture_interval(k, n, confidence)
    return clopper_pearson(k, n, 1.0 - (1.0 - confidence) / looks_possible)


def _check_budget(max_runs: int, batch: int) -> tuple[int, int]:
    max_runs, batch = count("max_runs", max_runs, 1), count("batch", batch, 1)
    return max_runs, min(batch, max_runs)


def confidence_sequence(
    sample: Sampler,
    p_required: float,
    confidence: float = 0.95,
    max_runs: int = 10_000,
    batch: int = 50,
    method: str = "mixture",
) -> SequentialResult:
    """Simulate in batches until the any-time interval lies wholly above or below ``p_required``.

    A wrong verdict (or a final interval missing the true p) has probability at most 1 - ``confidence``
    whatever the stopping time. UNDECIDED when ``max_runs`` are used up first.
    """
    p_required = probability("p_required", p_required, open_interval=False)
    confidence = probability("confidence", confidence)
    max_runs, batch = _check_budget(max_runs, batch)
    if method not in ("mixture", "bonferroni"):
        raise ValueError(f"method must be 'mixture' or 'bonferroni', got {method!r}")
    looks_possible = math.ceil(max_runs / batch)
    n = k = 0
    low, high = 0.0, 1.0
    looks: list[Look] = []
    verdict = Verdict.UNDECIDED
    while n < max_runs and verdict is Verdict.UNDECIDED:
        got = _draw(sample, min(batch, max_runs - n))
        n, k = n + got.size, k + int(got.sum())
        lo, hi = _interval(method, k, n, confidence, looks_possible)
        low, high = max(low, lo), min(high, hi)
        looks.append(Look(n, k, low, high))
        verdict = verdict_of(low, high, p_required)
    return SequentialResult(
        verdict, n, k, low, high, confidence, f"confidence-sequence/{method}", max_runs, batch, looks
    )


@dataclass(frozen=True)
class _Sprt:
    """Wald's thresholds and per-run log-likelihood-ratio increments of the test p0 vs p1."""

    p0: float
    p1: float
    log_a: float  # PASS at llr >= log_a = log((1 - beta) / alpha)
    log_b: float  # FAIL at llr <= log_b = log(beta / (1 - alpha))
    up: float  # llr increment of a success, log(p1 / p0)
    down: float  # llr increment of a failure, log((1 - p1) / (1 - p0))


def _sprt_design(p_required: float, delta: float, alpha: float, beta: float) -> _Sprt:
    p_required = probability("p_required", p_required)
    delta = probability("delta", delta)
    alpha, beta = probability("alpha", alpha), probability("beta", beta)
    p0, p1 = p_required - delta, p_required + delta
    if not (0.0 < p0 and p1 < 1.0):
        raise ValueError(f"the indifference region p_required +- delta = [{p0:g}, {p1:g}] must lie inside (0, 1)")
    if alpha + beta >= 1.0:
        raise ValueError(f"alpha + beta must be < 1, got {alpha + beta:g}")
    return _Sprt(
        p0,
        p1,
        math.log((1 - beta) / alpha),
        math.log(beta / (1 - alpha)),
        math.log(p1 / p0),
        math.log((1 - p1) / (1 - p0)),
    )


def sprt(
    sample: Sampler,
    p_required: float,
    delta: float = 0.05,
    alpha: float = 0.05,
    beta: float = 0.05,
    max_runs: int = 10_000,
    batch: int = 10,
    confidence: float = 0.95,
) -> SequentialResult:
    """Wald's SPRT of p <= p_required - delta (FAIL) vs p >= p_required + delta (PASS), checked after each batch.

    ``alpha``: probability of PASS when p = p_required - delta (and below); ``beta``: probability of FAIL
    when p = p_required + delta (and above). UNDECIDED if ``max_runs`` are used up first. The returned
    interval is the beta-binomial mixture confidence sequence at ``confidence`` on the same runs, valid at
    this data-dependent stopping time (computed once, at the stop: the looks carry the llr only).
    """
    d = _sprt_design(p_required, delta, alpha, beta)
    confidence = probability("confidence", confidence)
    max_runs, batch = _check_budget(max_runs, batch)
    n = k = 0
    llr = 0.0
    looks: list[Look] = []
    verdict = Verdict.UNDECIDED
    while n < max_runs and verdict is Verdict.UNDECIDED:
        got = _draw(sample, min(batch, max_runs - n))
        s = int(got.sum())
        n, k = n + got.size, k + s
        llr += s * d.up + (got.size - s) * d.down
        looks.append(Look(n, k, llr=llr))
        if llr >= d.log_a:
            verdict = Verdict.PASS
        elif llr <= d.log_b:
            verdict = Verdict.FAIL
    low, high = mixture_interval(k, n, confidence)  # any-time valid, so valid at this stopping time
    return SequentialResult(verdict, n, k, low, high, confidence, "sprt", max_runs, batch, looks)


def sprt_expected_runs(
    p: float, p_required: float, delta: float = 0.05, alpha: float = 0.05, beta: float = 0.05
) -> float:
    """Wald's approximation of the SPRT's expected number of runs when the true probability is ``p``.

    E[N] = (L log B + (1 - L) log A) / E[z], with L = P(FAIL) = (A^h - 1) / (A^h - B^h) where h != 0 solves
    p (p1/p0)^h + (1-p) ((1-p1)/(1-p0))^h = 1; at E[z] = 0 it is -log A log B / E[z^2]. Overshoot is
    ignored, so realised means with batch 1 lie slightly above it (and more above with larger batches).
    """
    d = _sprt_design(p_required, delta, alpha, beta)
    p = probability("p", p, open_interval=False)
    drift = p * d.up + (1 - p) * d.down
    if abs(drift) < 1e-12:
        return -d.log_a * d.log_b / (p * d.up**2 + (1 - p) * d.down**2)

    def phi(h: float) -> float:
        return p * math.exp(h * d.up) + (1 - p) * math.exp(h * d.down) - 1.0

    if p in (0.0, 1.0):  # every increment equal: the threshold is reached deterministically
        return float(math.ceil((d.log_b if p == 0.0 else d.log_a) / drift))
    sign = -1.0 if drift > 0 else 1.0  # the nonzero root lies on the side opposite to the drift
    far = sign
    while phi(far) <= 0:
        far *= 2
    h = optimize.brentq(phi, sign * 1e-9, far)
    big_a, big_b = h * d.log_a, h * d.log_b  # logs of A^h and B^h
    oc = math.expm1(big_a) / (math.exp(big_a) - math.exp(big_b))
    return (oc * d.log_b + (1 - oc) * d.log_a) / drift


def fixed_sample_size(
    p_required: float, delta: float = 0.05, alpha: float = 0.05, beta: float = 0.05, limit: int = 1_000_000
) -> tuple[int, int]:
    """The smallest n (and its critical count c) of the fixed-size exact test with the SPRT's error rates.

    The test passes at >= c successes of n; it needs P(X >= c | p0) <= alpha and P(X < c | p1) <= beta
    with X ~ Binomial(n, p). This is the run count the SPRT's expected runs are compared with.
    """
    d = _sprt_design(p_required, delta, alpha, beta)
    z = stats.norm.ppf(1 - alpha) * math.sqrt(d.p0 * (1 - d.p0)) + stats.norm.ppf(1 - beta) * math.sqrt(
        d.p1 * (1 - d.p1)
    )
    start = max(1, int(0.5 * (z / (d.p1 - d.p0)) ** 2))  # half the normal-approximation size: below the exact one
    for n in range(start, limit + 1):
        c = int(stats.binom.isf(alpha, n, d.p0)) + 1  # smallest c with P(X >= c | p0) <= alpha
        while c > 0 and stats.binom.sf(c - 2, n, d.p0) <= alpha:
            c -= 1
        if c <= n and stats.binom.cdf(c - 1, n, d.p1) <= beta:
            return n, c
    raise ValueError(f"no fixed sample size up to {limit} reaches alpha={alpha:g}, beta={beta:g}")

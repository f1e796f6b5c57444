"""Exact (Clopper-Pearson) binomial intervals for P(goal) and the PASS / FAIL / UNDECIDED verdict.

Why exact: verdicts are often drawn from few runs (10 field tests), where the normal approximation
covers far less than it claims near 0 or 1. Clopper-Pearson inverts two one-sided binomial tests,
so each side errs with probability at most alpha/2 for every true p (it is conservative, never
liberal). The bounds are beta quantiles: lower = Beta(alpha/2; k, n-k+1), upper = Beta(1-alpha/2;
k+1, n-k), with lower = 0 at k = 0 and upper = 1 at k = n.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Any

from scipy import special

from ._checks import count, probability


class Verdict(str, Enum):
    """The answer to "does the goal hold with probability at least p_required?"."""

    PASS = "PASS"  # the whole interval lies at or above p_required
    FAIL = "FAIL"  # the whole interval lies below p_required
    UNDECIDED = "UNDECIDED"  # the interval straddles p_required: more runs are needed


def clopper_pearson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The exact two-sided interval for a binomial proportion from ``k`` successes in ``n`` runs.

    ``n = 0`` gives the vacuous [0, 1]: no runs, no knowledge.
    """
    n = count("n", n)
    k = count("k", k)
    if k > n:
        raise ValueError(f"k must be <= n, got k={k}, n={n}")
    alpha = 1.0 - probability("confidence", confidence)
    # special.betaincinv(a, b, q) is stats.beta.ppf(q, a, b) without its ~100 us of argument handling per call
    lo = 0.0 if k == 0 else float(special.betaincinv(k, n - k + 1, alpha / 2))
    hi = 1.0 if k == n else float(special.betaincinv(k + 1, n - k, 1 - alpha / 2))
    return lo, hi


def verdict_of(low: float, high: float, p_required: float) -> Verdict:
    """PASS if ``low >= p_required``, FAIL if ``high < p_required``, UNDECIDED otherwise."""
    if low >= p_required:
        return Verdict.PASS
    if high < p_required:
        return Verdict.FAIL
    return Verdict.UNDECIDED


@dataclass(frozen=True)
class BinomialDecision:
    """A verdict with the interval and the runs it rests on."""

    verdict: Verdict
    k: int  # runs that met the goal
    n: int  # runs
    p_required: float
    confidence: float  # of the two-sided interval; each wrong verdict has probability <= (1 - confidence)/2
    low: float
    high: float

    @property
    def p_hat(self) -> float:
        return self.k / self.n if self.n else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict.value,
            "k": self.k,
            "n": self.n,
            "p_hat": self.p_hat if self.n else None,
            "p_required": self.p_required,
            "confidence": self.confidence,
            "interval": [self.low, self.high],
            "method": "clopper-pearson",
        }


def decide(k: int, n: int, p_required: float, alpha: float = 0.05) -> BinomialDecision:
    """Decide from ``k`` of ``n`` runs meeting the goal, with the two-sided 1 - ``alpha`` exact interval.

    PASS when its lower bound is >= ``p_required``, FAIL when its upper bound is < ``p_required``,
    otherwise UNDECIDED. Whatever the true p, a PASS (or a FAIL) is wrong with probability at most
    ``alpha / 2``.
    """
    p_required = probability("p_required", p_required, open_interval=False)
    confidence = 1.0 - probability("alpha", alpha)
    lo, hi = clopper_pearson(k, n, confidence)
    return BinomialDecision(verdict_of(lo, hi, p_required), int(k), int(n), p_required, confidence, lo, hi)

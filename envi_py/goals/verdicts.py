"""Whether a requirement holds with its declared probability, from a finite number of runs.

A requirement must hold with probability at least p (``RequirementSpec.probability``). From R runs of
which k satisfy it, the fraction k/R is only an estimate, so the verdict uses the exact
(Clopper-Pearson) interval of the satisfaction probability (``scipy.stats.binomtest``): *holds*
when the interval lies at or above p, *fails* when it lies below p, *undecided* otherwise (more
runs are needed). The interval is exact, hence conservative: it never claims more than R runs show.
"""

from __future__ import annotations

from dataclasses import dataclass

from scipy import stats

from ..system import RequirementSpec
from .evaluate import Runs
from .requirements import satisfied


@dataclass(frozen=True)
class Verdict:
    """How many of ``runs`` runs satisfied the requirement, the interval and the verdict."""

    name: str
    probability: float
    satisfied: int
    runs: int
    low: float
    high: float
    confidence: float
    verdict: str  # "holds", "fails" or "undecided"

    @property
    def fraction(self) -> float:
        return self.satisfied / self.runs

    def to_json(self) -> dict[str, object]:
        return {
            "name": self.name,
            "probability": self.probability,
            "satisfied": self.satisfied,
            "runs": self.runs,
            "fraction": self.fraction,
            "interval": [self.low, self.high],
            "confidence": self.confidence,
            "verdict": self.verdict,
        }


def verdict(req: RequirementSpec, runs: Runs, confidence: float = 0.95) -> Verdict:
    """The verdict on ``req`` from ``runs`` at the given two-sided confidence."""
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie strictly between 0 and 1, not {confidence!r}")
    ok = satisfied(req, runs)
    k, n = int(ok.sum()), int(ok.size)
    ci = stats.binomtest(k, n).proportion_ci(confidence_level=confidence, method="exact")
    word = "holds" if ci.low >= req.probability else "fails" if ci.high < req.probability else "undecided"
    return Verdict(req.name, req.probability, k, n, float(ci.low), float(ci.high), confidence, word)

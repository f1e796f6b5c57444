"""Verdicts about the REAL system's P(goal) from many simulated runs plus a few real ones.

Prediction-powered inference (PPI, Angelopoulos et al. 2023). Let f(s) be the model's probability
that a run started from the initial window s (sigma_0) meets the goal, estimated by simulating from s.

* ``sim_predictions``: f over N simulated starts (per-run 0/1 outcomes, or per-start probabilities),
  the starts drawn like the real runs' starts. If they are only the real runs' own starts, PPI gains
  nothing (it collapses to the real mean): the gain comes from starts without a real run.
* ``real_outcomes`` Y_i and ``paired_predictions`` f(s_i): each real run and the simulated
  satisfaction probability from its own sigma_0.

theta_PPI = mean(f over sims) + mean(Y_i - f(s_i)). The second term, the rectifier, removes the model's
bias whatever it is, so theta_PPI is unbiased for the real P(goal); its variance is
var(f)/N + var(Y - f)/n, with var(Y - f) at least the model's own mean f (1 - f) (see ``_rectified``),
and the interval is theta +- t se, the Student t quantile at the Welch-Satterthwaite degrees of freedom of
the two variance terms (about n - 1 when the real runs' sample variance sets the second; the normal
quantile when the model's own variance does, since that one is not estimated from the n runs): the
PPI paper's normal quantile assumes n large, and its sample variance of the rectifier comes from the
same few runs.
It is narrower than the real-only one only as far as the start explains the outcome (var(Y - f) < var(Y));
with a model that predicts nothing from the start it is about as wide as the real-only interval.

The control-variate estimator (PPI++ "power tuning") uses c * f instead of f, with
c = cov(Y, f) / var(f) from the paired runs: never much worse than real-only when f is uninformative.

Validity check: the rectifier mean is the model's measured error on this version (reported with its t
interval). The claim is WITHDRAWN when an exact test of calibration rejects at ``check_level``: if the
model is calibrated, the number of real runs meeting the goal is Poisson-binomial with the paired
predictions as probabilities (independent runs), and the two-sided p-value sums the probabilities of all
counts no likelier than the observed one (as ``scipy.stats.binomtest``). Predictions estimated from m
simulated runs per start are shrunk to (m f + 1/2) / (m + 1) for this test (``sims_per_start``), so a
start where the model saw no failure in m runs is "rare", not "impossible". Using the model's own
variance makes this far more powerful at 10 runs than a t test of the rectifier mean (whose sample
variance is tiny when no surprising run was drawn).

The 0/1 outcomes still hide most of what the paired runs show: when the start decides the outcome
(each start's m simulated runs all pass or all fail, and agree with the real run) a model whose error
lies in the rare starts looks perfect on 10 runs. So, when the requirement's margins are given (how far
inside or outside its threshold each run ends: a metric's distance to its threshold, an STL formula's
robustness), the check also asks whether each real run's margin is a plausible draw from its own m
simulated margins: under a faithful model the real run and its m paired runs are exchangeable, so the
real run's rank among the m + 1 (ties broken at random) is uniform, and its randomised probability
integral transform (PIT) is exactly Uniform(0, 1) at any n and m. A Cramer-von Mises test of the n PIT
values against the uniform (``scipy.stats.cramervonmises``) catches a model that is biased (PITs piled
at one end) or too narrow or too wide (PITs at both ends, or in the middle) long before the outcomes
disagree.

A margin is still one number per run, and a model can match it in 10 real runs while its runs look
unlike the real ones: the car twin's slightly wrong model (motor lag 0.20 s against 0.15, colour noise
2.0 against 1.5) kept its lane claim in 10 % of repetitions, and those kept claims covered 81-88 %:
the check keeps exactly the repetitions whose real runs look like the model, and those are the ones
whose rectifier under-corrects. So the same PIT test also runs on summaries of every run
(``summaries``; :func:`trace_summaries`: the mean, spread and roughness of each signal the requirement
reads), which any run shows whatever its outcome. A model that gets them wrong is contradicted by
every real run, not only by the few near the threshold. The tests share the level (Bonferroni: count,
margins and k summaries at ``level / (2 + k)`` each), so a faithful model's claim is withdrawn with
probability at most ``level``. On withdrawal the interval falls back to the exact real-only
(Clopper-Pearson) interval and the verdict says why: a user should not be told P(goal) "from 4000
simulated runs" by a model the real runs contradict. A kept claim has ruled out only what the tests
could see: the reported n says how few runs back the check, and every check states the smallest error
in P(goal) its count test catches 80 % of the time from those runs (:func:`detectable_error`).

Versions never field-tested (TMVU): :func:`model_only` states that the verdict rests on the model only
and carries the model's measured error on the versions that have real runs beside it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from ._checks import count, outcomes, probability, unit_vector
from .binomial import BinomialDecision, Verdict, clopper_pearson, decide, verdict_of


@dataclass(frozen=True)
class RectifierCheck:
    """The model's measured error on one version: the rectifier Y - f over its paired real runs."""

    n: int
    mean: float  # mean(real outcome - paired prediction): the model's measured error
    sd: float
    low: float  # two-sided (1 - level) t interval of the rectifier mean
    high: float
    p_value: float  # of the exact Poisson-binomial calibration test
    level: float
    margin_p_value: float | None = None  # of the PIT uniformity test of the margins (None: no margins given)
    #: PIT uniformity test p-value of each run summary of the signals the requirement reads (see
    #: :func:`trace_summaries`), by name: "color roughness" (empty: none given)
    summary_p_values: Mapping[str, float] = field(default_factory=dict)
    #: the smallest error in every start's P(goal), down and up, that the count test catches with
    #: probability DETECTION_POWER from these runs (None: no error within [0, 1] is caught that often)
    detectable_down: float | None = None
    detectable_up: float | None = None

    @property
    def detectable_text(self) -> str:
        """The check's power in words: a kept claim rules out only errors the check would have seen."""
        caught = [
            f"a {word} of {d:.2f}" for word, d in (("drop", self.detectable_down), ("rise", self.detectable_up)) if d
        ]
        if not caught:
            return f"from {self.n} runs the count test catches no error in P(goal) {DETECTION_POWER:.0%} of the time"
        missed = [word for word, d in (("drop", self.detectable_down), ("rise", self.detectable_up)) if not d]
        return (
            f"from {self.n} runs the count test catches {' or '.join(caught)} in every start's P(goal) "
            f"{DETECTION_POWER:.0%} of the time" + (f", and cannot catch a {missed[0]}" if missed else "") + "; "
            "smaller errors can pass it"
        )

    @property
    def pit_p_values(self) -> dict[str, float]:
        """Every PIT test's p-value by what it tests: "margin" (when margins were given), then each
        run summary's name."""
        margin = {} if self.margin_p_value is None else {"margin": self.margin_p_value}
        return {**margin, **self.summary_p_values}

    @property
    def tests(self) -> int:
        """How many tests share the level: the count test and each PIT test."""
        return 1 + len(self.pit_p_values)

    @property
    def test_level(self) -> float:
        """The level each test withdraws at: the whole level shared among the tests (Bonferroni), so a
        reported p of 0.03 beside a kept claim is no contradiction."""
        return self.level / self.tests

    @property
    def passed(self) -> bool:
        """No test rejects at its share of the level: the real runs do not contradict the model."""
        return min([self.p_value, *self.pit_p_values.values()]) > self.test_level

    @property
    def failed_test(self) -> str | None:
        """Which test withdrew the claim, in words, or None when the check passed."""
        if self.passed:
            return None
        for name, p in self.pit_p_values.items():
            if p > self.test_level:
                continue
            if name == "margin":
                return f"the real margins are not plausible draws from the paired simulations (PIT test p = {p:.3g})"
            return f"the real runs' {name} is not a plausible draw from the paired simulations' (PIT test p = {p:.3g})"
        return (
            "the count of real runs meeting the goal contradicts the predictions "
            f"(calibration test p = {self.p_value:.3g})"
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "mean": self.mean,
            "sd": self.sd,
            "interval": [self.low, self.high],
            "p_value": self.p_value,
            "margin_p_value": self.margin_p_value,
            "summary_p_values": dict(self.summary_p_values),
            "detectable_error": {
                "power": DETECTION_POWER,
                "down": self.detectable_down,
                "up": self.detectable_up,
                "meaning": "smallest shift of every start's P(goal) the count test rejects with this power",
            },
            "level": self.level,
            "passed": self.passed,
            "test": "exact two-sided Poisson-binomial test of the count of real runs meeting the goal, "
            "paired predictions as probabilities"
            + (
                ""
                if self.tests == 1
                else "; and Cramer-von Mises tests of the randomised PIT of each real run's "
                + " and ".join(self.pit_p_values)
                + f" among its paired simulated runs' (each of the {self.tests} tests at level / {self.tests})"
            ),
        }


def _paired(real_outcomes: object, paired_predictions: object) -> tuple[np.ndarray, np.ndarray]:
    y = outcomes("real_outcomes", real_outcomes, 2).astype(np.float64)
    f = unit_vector("paired_predictions", paired_predictions, 2)
    if y.size != f.size:
        raise ValueError(f"real_outcomes ({y.size}) and paired_predictions ({f.size}) must pair run by run")
    return y, f


def _poisson_binomial(probabilities: np.ndarray) -> np.ndarray:
    """pmf of the number of successes of independent Bernoulli(probabilities), by convolution (O(n^2),
    fine for thousands of runs; scipy has no Poisson-binomial distribution)."""
    pmf = np.array([1.0])
    for p in probabilities:
        pmf = np.convolve(pmf, [1.0 - p, p])
    return pmf


def _count_p_values(pmf: np.ndarray) -> np.ndarray:
    """Two-sided p-value of every count: the probability of all counts no likelier than it (relative
    tolerance 1e-7 for ties, as scipy.stats.binomtest does)."""
    return np.array([min(1.0, float(pmf[pmf <= q * (1 + 1e-7)].sum())) for q in pmf])


def calibration_p_value(real_outcomes: np.ndarray, probabilities: np.ndarray) -> float:
    """Exact two-sided p-value of the count of successes under independent Bernoulli(probabilities)."""
    return float(_count_p_values(_poisson_binomial(probabilities))[int(np.sum(real_outcomes))])


#: the power at which a check states the smallest model error it catches
DETECTION_POWER = 0.8


def detectable_error(
    probabilities: np.ndarray, level: float, power: float = DETECTION_POWER
) -> tuple[float | None, float | None]:
    """The smallest shifts (down, up; steps of 0.01) of every start's probability that the count test at
    ``level`` rejects with probability ``power``; None where no shift within [0, 1] does.

    Why: a kept claim says only that the few real runs did not contradict the model. With 10 runs the
    count test misses errors of 0.2-0.4 in P most of the time, and the repetitions it keeps are those
    where the model's error hid (benchmarks/coverage_twin.py), so a reader must see how large an error
    the check could have seen. The shifted probabilities are clipped to [0, 1].
    """
    g = np.asarray(probabilities, dtype=np.float64)
    reject = _count_p_values(_poisson_binomial(g)) <= level
    shifts = np.arange(1, 101) / 100

    def first(sign: float) -> float | None:
        for d in shifts:
            if _poisson_binomial(np.clip(g + sign * d, 0.0, 1.0))[reject].sum() >= power:
                return float(d)
        return None

    return first(-1.0), first(1.0)


def _margins(name: str, values: object, ndim: int) -> np.ndarray:
    """Margins as a float array of ``ndim`` dimensions; +-inf is a margin (a metric that never settles),
    NaN is not."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numbers: {exc}") from None
    if a.ndim != ndim:
        what = "one per real run" if ndim == 1 else "(real runs, simulations)"
        raise ValueError(f"{name} must be {what}, got shape {a.shape}")
    if np.isnan(a).any():
        raise ValueError(f"{name} hold {int(np.isnan(a).sum())} NaN values")
    return a


def pit_values(real_margins: object, paired_margins: object, seed: int = 0) -> np.ndarray:
    """Randomised PIT of each real margin among its own paired simulated margins, (n,) in (0, 1).

    ``paired_margins`` is (n, m): row i holds the m simulated margins from real run i's start. The rank
    of the real value among the m + 1, ties broken uniformly at random (``seed``, so a verdict repeats),
    scaled to (0, 1): exactly uniform when the m + 1 are exchangeable.
    """
    real, sims = _margins("real_margins", real_margins, 1), _margins("paired_margins", paired_margins, 2)
    if real.size < 1 or sims.shape[0] != real.size or sims.shape[1] < 1:
        raise ValueError(f"paired_margins must be (real runs, simulations) = ({real.size}, m), got {sims.shape}")
    m = sims.shape[1]
    below = (sims < real[:, None]).sum(axis=1)
    ties = (sims == real[:, None]).sum(axis=1)
    u = np.random.default_rng(seed).random(real.size)
    return (below + u * (ties + 1)) / (m + 1)


def margin_p_value(real_margins: object, paired_margins: object, seed: int = 0) -> float:
    """p-value of the Cramer-von Mises test that the real margins' PIT values are Uniform(0, 1)."""
    return float(stats.cramervonmises(pit_values(real_margins, paired_margins, seed), "uniform").pvalue)


def trace_summaries(trace: object) -> dict[str, np.ndarray]:
    """What the validity check compares of each run besides its margin: of one signal's scored samples
    (runs, samples), each run's mean, standard deviation and roughness (mean absolute step), (runs,).

    Why these: a requirement's margin is one number per run, and a model can match it in 10 real runs
    while its runs look nothing like the real ones (the car twin's slightly wrong model: colour noise 2.0
    against 1.5, its lane claims kept in 10-20 % of repetitions and covering 80-95 % when kept). Level,
    spread and roughness of the signals the requirement reads are what any run shows, and a model that
    gets them wrong has no standing to predict the requirement's outcome from the starts without a real
    run. Under a faithful model each is exchangeable with its paired simulations, as the margin is.
    """
    x = np.asarray(trace, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < 2:
        raise ValueError(f"a trace must be (runs, samples) with at least 2 samples, got shape {x.shape}")
    return {
        "mean": x.mean(axis=1),
        "spread": x.std(axis=1),
        "roughness": np.abs(np.diff(x, axis=1)).mean(axis=1),
    }


def rectifier_check(
    real_outcomes: object,
    paired_predictions: object,
    level: float = 0.05,
    sims_per_start: int | None = None,
    real_margins: object | None = None,
    paired_margins: object | None = None,
    seed: int = 0,
    summaries: Mapping[str, tuple[object, object]] | None = None,
) -> RectifierCheck:
    """The model's measured error on paired real runs (at least 2) and its validity check at ``level``.

    ``sims_per_start``: how many simulated runs each paired prediction was estimated from (None: the
    predictions are exact probabilities); used to shrink the predictions for the test (module docstring).
    ``real_margins`` (n,) and ``paired_margins`` (n, m), given together: the requirement's margin of each
    real run and of its paired simulated runs; they add the PIT test. ``summaries``: more such pairs by
    name (real (n,), paired (n, m)), each adding its PIT test (:func:`trace_summaries`). The tests
    share ``level`` equally (Bonferroni), so a faithful model's claim is withdrawn at most that often.
    """
    y, f = _paired(real_outcomes, paired_predictions)
    level = probability("level", level)
    g = _shrunk(f, sims_per_start)
    p = calibration_p_value(y, g)
    if (real_margins is None) != (paired_margins is None):
        raise ValueError("real_margins and paired_margins go together: give both or neither")
    p_margin = None
    if real_margins is not None:
        if np.asarray(real_margins).shape != y.shape:
            raise ValueError(f"real_margins must hold one margin per real run ({y.size})")
        p_margin = margin_p_value(real_margins, paired_margins, seed)
    p_summaries = {}
    for name, (real_values, paired_values) in (summaries or {}).items():
        if np.asarray(real_values).shape != y.shape:
            raise ValueError(f"summary {name!r} must hold one value per real run ({y.size})")
        p_summaries[name] = margin_p_value(real_values, paired_values, seed)
    r = y - f
    mean, sd = float(r.mean()), float(r.std(ddof=1))
    if np.ptp(r) <= 1e-12:
        # every real run off by the same amount (all met the goal, say, where the model said they would):
        # no spread to estimate from, yet 0/1 outcomes do not make the error known. The exact
        # (Clopper-Pearson) interval of the real share, less the mean prediction, bounds it instead: 30
        # of 30 real runs allow a real P(goal) down to 0.884, so an error down to -0.116, not +-0.
        cp_lo, cp_hi = clopper_pearson(int(y.sum()), y.size, 1.0 - level)
        sd, lo, hi = 0.0, min(mean, cp_lo - float(f.mean())), max(mean, cp_hi - float(f.mean()))
    else:
        lo, hi = (float(b) for b in stats.ttest_1samp(r, 0.0).confidence_interval(1.0 - level))
    check = RectifierCheck(r.size, mean, sd, lo, hi, p, level, p_margin, p_summaries)
    down, up = detectable_error(g, check.test_level)
    return replace(check, detectable_down=down, detectable_up=up)


@dataclass(frozen=True)
class Estimate:
    """A point estimate of the real P(goal) with its interval and what it rests on."""

    method: str  # "ppi" or "control-variate"
    estimate: float
    se: float
    low: float
    high: float
    confidence: float
    coefficient: float  # c multiplying the prediction (1 for PPI)
    n_real: int
    n_sim: int
    df: float = math.inf  # degrees of freedom of the t quantile (Welch-Satterthwaite)

    def to_json(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "estimate": self.estimate,
            "se": self.se,
            "interval": [self.low, self.high],
            "confidence": self.confidence,
            "coefficient": self.coefficient,
            "n_real": self.n_real,
            "n_sim": self.n_sim,
            "df": self.df if math.isfinite(self.df) else None,
        }


def _shrunk(f: np.ndarray, sims_per_start: int | None) -> np.ndarray:
    """Predictions estimated from m simulated runs as (m f + 1/2) / (m + 1): a start where the model saw
    no failure in m runs is "rare", not "impossible" (None: the predictions are exact probabilities)."""
    if sims_per_start is None:
        return f
    m = count("sims_per_start", sims_per_start, 1)
    return (m * f + 0.5) / (m + 1)


def _rectified(
    method: str,
    sim: np.ndarray,
    y: np.ndarray,
    f: np.ndarray,
    c: float,
    confidence: float,
    sims_per_start: int | None = None,
) -> Estimate:
    """theta = c mean(sim) + mean(Y - c f), variance c^2 var(sim)/N + var(Y - c f)/n, normal interval.

    var(Y - c f) is taken as at least mean(g (1 - g)), g the predictions shrunk as in :func:`_shrunk`:
    from 10 runs the sample variance is often far too small, because a run whose outcome the model did
    not foresee is rare and may not be among them (the interval then under-covers). For any c,
    var(Y - c f) >= E[var(Y | start)], which a calibrated model puts at E[f (1 - f)]; the shrinkage keeps
    a start whose m simulated runs all agreed from counting as certain (with f = 0 everywhere and 3 real
    failures the interval would otherwise be a point). The floor costs nothing when the sample variance
    is already that large.
    """
    r = y - c * f
    g = _shrunk(f, sims_per_start)
    v_sim = c**2 * float(sim.var(ddof=1)) / sim.size
    sample, floor = float(r.var(ddof=1)), float(np.mean(g * (1 - g)))
    v_real = max(sample, floor) / r.size
    se = float(np.sqrt(v_sim + v_real))
    # the floor is the model's own variance (from m simulated runs per start), not estimated from the n
    # residuals: it carries no t penalty (infinitely many degrees of freedom)
    df = welch_df(v_sim, sim.size, v_real, r.size if sample >= floor else math.inf)
    theta = c * float(sim.mean()) + float(r.mean())
    half = float(stats.t.ppf(0.5 + confidence / 2, df)) * se
    return Estimate(
        method, theta, se, max(0.0, theta - half), min(1.0, theta + half), confidence, c, y.size, sim.size, df
    )


def welch_df(v_a: float, n_a: float, v_b: float, n_b: float) -> float:
    """Welch-Satterthwaite degrees of freedom of ``v_a + v_b``, two variances of means estimated from
    ``n_a`` and ``n_b`` samples (``math.inf`` for a variance that is known rather than estimated; the
    result is ``inf`` when nothing is estimated: the sum is known)."""
    den = (v_a**2 / (n_a - 1) if n_a > 1 else 0.0) + (v_b**2 / (n_b - 1) if n_b > 1 else 0.0)
    return (v_a + v_b) ** 2 / den if den > 0 else math.inf


def ppi(
    sim_predictions: object,
    real_outcomes: object,
    paired_predictions: object,
    confidence: float = 0.95,
    sims_per_start: int | None = None,
) -> Estimate:
    """Prediction-powered estimate of the real P(goal) with its normal interval (see the module docstring).

    ``sims_per_start``: simulated runs behind each paired prediction (None: exact probabilities)."""
    sim = unit_vector("sim_predictions", sim_predictions, 2)
    y, f = _paired(real_outcomes, paired_predictions)
    return _rectified("ppi", sim, y, f, 1.0, probability("confidence", confidence), sims_per_start)


def control_variate(
    sim_predictions: object,
    real_outcomes: object,
    paired_predictions: object,
    confidence: float = 0.95,
    sims_per_start: int | None = None,
) -> Estimate:
    """Control-variate estimate: theta = mean(Y) - c (mean(f) - mean(sim)), c = cov(Y, f) / var(f) on the pairs.

    c = 0 when the paired predictions do not vary (they carry no information): the real-only mean.
    Estimating c from the same n runs adds a bias of order 1/n, negligible beside the interval.
    """
    sim = unit_vector("sim_predictions", sim_predictions, 2)
    y, f = _paired(real_outcomes, paired_predictions)
    var_f = float(f.var(ddof=1))
    c = float(np.cov(y, f, ddof=1)[0, 1]) / var_f if var_f > 0 else 0.0
    return _rectified("control-variate", sim, y, f, c, probability("confidence", confidence), sims_per_start)


@dataclass(frozen=True)
class RealSystemVerdict:
    """The verdict about the real system, what it rests on, and the real-only verdict beside it."""

    verdict: Verdict
    basis: str  # "model+real" (the model-based estimate holds) or "real-only" (the claim was withdrawn)
    low: float
    high: float
    p_required: float
    confidence: float
    model_estimate: Estimate  # reported even when withdrawn, so a reader sees what was refused
    real_only: BinomialDecision
    check: RectifierCheck
    reason: str

    @property
    def withdrawn(self) -> bool:
        return self.basis == "real-only"

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict.value,
            "basis": self.basis,
            "withdrawn": self.withdrawn,
            "interval": [self.low, self.high],
            "p_required": self.p_required,
            "confidence": self.confidence,
            "n_real": self.model_estimate.n_real,
            "n_sim": self.model_estimate.n_sim,
            "model_estimate": self.model_estimate.to_json(),
            "real_only": self.real_only.to_json(),
            "check": self.check.to_json(),
            "reason": self.reason,
        }


def ppi_verdict(
    sim_predictions: object,
    real_outcomes: object,
    paired_predictions: object,
    p_required: float,
    alpha: float = 0.05,
    check_level: float = 0.05,
    estimator: str = "ppi",
    sims_per_start: int | None = None,
    real_margins: object | None = None,
    paired_margins: object | None = None,
    seed: int = 0,
    summaries: Mapping[str, tuple[object, object]] | None = None,
) -> RealSystemVerdict:
    """PASS / FAIL / UNDECIDED for the real system at confidence 1 - ``alpha``, from sims plus paired real runs.

    ``estimator``: "ppi" or "control-variate". If the calibration check rejects at ``check_level`` the
    model-based claim is withdrawn and the verdict comes from the real runs alone (Clopper-Pearson).
    ``sims_per_start``: simulated runs behind each paired prediction; ``real_margins``/``paired_margins``
    (with ``seed`` for the PIT's ties): the requirement's margins, which add the PIT test, and
    ``summaries`` further run summaries, each adding one (see :func:`rectifier_check`).
    """
    if estimator not in ("ppi", "control-variate"):
        raise ValueError(f"estimator must be 'ppi' or 'control-variate', got {estimator!r}")
    p_required = probability("p_required", p_required, open_interval=False)
    confidence = 1.0 - probability("alpha", alpha)
    est = (ppi if estimator == "ppi" else control_variate)(
        sim_predictions, real_outcomes, paired_predictions, confidence, sims_per_start
    )
    y = outcomes("real_outcomes", real_outcomes, 2)
    real = decide(int(y.sum()), y.size, p_required, alpha)
    check = rectifier_check(
        real_outcomes, paired_predictions, check_level, sims_per_start, real_margins, paired_margins, seed, summaries
    )
    if not check.passed:
        reason = (
            f"claim withdrawn: the {check.n} real runs contradict the model: {check.failed_test}, "
            f"mean(real - predicted) = {check.mean:+.3f}; verdict from the {real.n} real runs alone"
        )
        return RealSystemVerdict(
            real.verdict, "real-only", real.low, real.high, p_required, confidence, est, real, check, reason
        )
    reason = (
        f"{est.method} from {est.n_sim} simulated starts and {est.n_real} paired real runs; model error "
        f"{check.mean:+.3f}, calibration test p = {check.p_value:.3g}"
        + ("" if check.margin_p_value is None else f", margin PIT test p = {check.margin_p_value:.3g}")
        + "".join(f", {name} PIT test p = {p:.3g}" for name, p in check.summary_p_values.items())
        + (
            f" (withdrawn at p <= {check.level:g})"
            if check.tests == 1
            else f" (each test withdraws at p <= {check.test_level:g}, "
            + ("half" if check.tests == 2 else f"1/{check.tests}")
            + f" of {check.level:g})"
        )
        + f"; {check.detectable_text}"
    )
    return RealSystemVerdict(
        verdict_of(est.low, est.high, p_required),
        "model+real",
        est.low,
        est.high,
        p_required,
        confidence,
        est,
        real,
        check,
        reason,
    )


@dataclass(frozen=True)
class ModelOnlyVerdict:
    """A verdict for a version without real runs: it rests on the model only."""

    verdict: Verdict
    low: float  # the model's own P(goal) interval (Clopper-Pearson over the simulated runs)
    high: float
    widened_low: float  # widened by the largest measured model error; the verdict uses these
    widened_high: float
    k: int
    n_sim: int
    p_required: float
    confidence: float
    measured_errors: dict[str, RectifierCheck]
    reason: str
    basis: str = "model only"

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict.value,
            "basis": self.basis,
            "model_interval": [self.low, self.high],
            "interval": [self.widened_low, self.widened_high],
            "k": self.k,
            "n_sim": self.n_sim,
            "p_required": self.p_required,
            "confidence": self.confidence,
            "measured_errors": {v: c.to_json() for v, c in self.measured_errors.items()},
            "reason": self.reason,
        }


#: The share of a never field-tested version's simulated runs that may leave the training data before
#: the model-only claim is refused: beyond it the verdict would rest on extrapolation.
MAX_OUTSIDE_SHARE = 0.1


def model_only(
    sim_outcomes: object,
    p_required: float,
    measured_errors: Mapping[str, RectifierCheck],
    alpha: float = 0.05,
    left_training: tuple[int, int] = (0, 0),
) -> ModelOnlyVerdict:
    """The verdict for a never field-tested version, with the model's measured error carried beside it.

    The model's P(goal) interval is Clopper-Pearson over the simulated runs. The real system may differ by
    the model's error, which was measured only on other versions (``measured_errors``: their rectifier
    checks). The verdict uses the interval widened by the largest |bound| of those rectifier intervals:
    an assumption (the error transfers to this version), not a guarantee, and the reason says so. No
    measured versions, or a version whose check failed, leave the verdict UNDECIDED; so do simulated
    runs that leave the training data (``left_training``: how many of how many) beyond
    :data:`MAX_OUTSIDE_SHARE`, since the measured error says nothing about where the model never was.
    """
    y = outcomes("sim_outcomes", sim_outcomes, 1)
    p_required = probability("p_required", p_required, open_interval=False)
    confidence = 1.0 - probability("alpha", alpha)
    k, n = int(y.sum()), y.size
    lo, hi = clopper_pearson(k, n, confidence)
    errors = dict(measured_errors)
    failed = sorted(v for v, c in errors.items() if not c.passed)
    outside, examined = left_training
    if examined and outside > MAX_OUTSIDE_SHARE * examined:
        wl, wh = 0.0, 1.0
        reason = (
            f"rests on the model only, and {outside} of its {examined} simulated runs leave the training data "
            f"(states or commands where the model was never trained): extrapolation, no claim"
        )
    elif not errors:
        wl, wh = 0.0, 1.0
        reason = "rests on the model only, and no version has real runs to measure the model's error: no claim"
    elif failed:
        wl, wh = 0.0, 1.0
        reason = (
            f"rests on the model only, and the model failed its validity check on {', '.join(failed)}: "
            f"no claim for a version without real runs"
        )
    else:
        bound = max(max(abs(c.low), abs(c.high)) for c in errors.values())
        wl, wh = max(0.0, lo - bound), min(1.0, hi + bound)
        runs = sum(c.n for c in errors.values())
        reason = (
            f"rests on the model only ({n} simulated runs, no real runs of this version); the model's error "
            f"measured on {len(errors)} other version(s) ({runs} real runs) is up to +-{bound:.3f}, and the "
            f"interval is widened by it assuming the error transfers to this version"
        )
    return ModelOnlyVerdict(
        verdict_of(wl, wh, p_required), lo, hi, wl, wh, k, n, p_required, confidence, errors, reason
    )

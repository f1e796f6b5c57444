"""PPI coverage and width on synthetic paired runs, a control-variate case by hand, withdrawal, model-only verdicts."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from scipy import stats

from envi_py.verdicts import (
    Verdict,
    clopper_pearson,
    control_variate,
    model_only,
    pit_values,
    ppi,
    ppi_verdict,
    rectifier_check,
    trace_summaries,
)
from envi_py.verdicts.real_system import calibration_p_value, detectable_error, welch_df

SIMS_PER_START, STARTS = 20, 400


def expit(z: np.ndarray) -> np.ndarray:
    return 1 / (1 + np.exp(-z))


def synthetic(rng: np.random.Generator, n_real: int, slope: float, shift: float = 0.0):
    """Starts x ~ N(0, 1); the real run meets the goal with p(x) = expit(2 + slope x); the model's p is
    expit(2 + shift + slope x), estimated from 20 simulated runs per start (the paired prediction)."""
    x = rng.normal(size=n_real)
    y = rng.random(n_real) < expit(2 + slope * x)
    paired = rng.binomial(SIMS_PER_START, expit(2 + shift + slope * x)) / SIMS_PER_START
    xs = rng.normal(size=STARTS)
    sims = rng.binomial(SIMS_PER_START, expit(2 + shift + slope * xs)) / SIMS_PER_START
    return sims, y, paired


def true_rate(slope: float) -> float:
    z, w = np.polynomial.hermite_e.hermegauss(80)  # E[expit(2 + slope X)], X ~ N(0, 1), by quadrature
    return float(np.sum(w * expit(2 + slope * z)) / np.sqrt(2 * np.pi))


def test_ppi_covers_and_is_narrower_than_real_only_with_a_faithful_model():
    """500 repetitions, 10 real runs each; the start explains most of the outcome (slope 8)."""
    rng, truth, reps = np.random.default_rng(0), true_rate(8.0), 500
    covered, ratio = [], []
    for _ in range(reps):
        sims, y, paired = synthetic(rng, 10, 8.0)
        est = ppi(sims, y, paired)
        lo, hi = clopper_pearson(int(y.sum()), y.size)
        covered.append(est.low <= truth <= est.high)
        ratio.append((est.high - est.low) / (hi - lo))
    assert np.mean(covered) >= 0.93
    assert np.median(ratio) <= 0.6


def test_verdict_keeps_the_claim_with_a_faithful_model_and_covers():
    rng, truth, reps = np.random.default_rng(1), true_rate(8.0), 300
    verdicts = [
        ppi_verdict(*synthetic(rng, 10, 8.0), p_required=0.5, sims_per_start=SIMS_PER_START) for _ in range(reps)
    ]
    assert np.mean([v.withdrawn for v in verdicts]) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / reps)
    assert np.mean([v.low <= truth <= v.high for v in verdicts]) >= 0.93


def test_control_variate_by_hand():
    y = np.array([1, 0, 1, 1])
    f = np.array([0.9, 0.2, 0.6, 0.7])
    sims = np.array([0.5, 0.7, 0.3, 0.4, 0.6])
    # cov(y, f) = (0.25*0.3 + 0.75*0.4 + 0 + 0.25*0.1) / 3 = 0.4/3; var(f) = (0.09+0.16+0+0.01)/3 = 0.26/3
    c = 0.4 / 0.26
    theta = 0.75 - c * (0.6 - 0.5)
    # var(y - c f) = 0.044872 lies below the model's own mean f(1-f) = (0.09+0.16+0.24+0.21)/4 = 0.175: the floor
    assert (y - c * f).var(ddof=1) == pytest.approx(0.044872, abs=1e-6)
    se2 = 0.175 / 4 + c**2 * 0.1 / 4 / 5  # sims: squared deviations sum to 0.1
    est = control_variate(sims, y, f)
    assert est.coefficient == pytest.approx(1.5384615, abs=1e-7)
    assert est.estimate == pytest.approx(0.5961538, abs=1e-7) == pytest.approx(theta)
    assert est.se == pytest.approx(np.sqrt(se2), rel=1e-12) == pytest.approx(0.235763, abs=1e-6)
    # the floor (the model's own variance) is known, not estimated from the 4 runs: only the 5 simulated
    # predictions' term counts, Welch-Satterthwaite (v_sim + v_real)^2 / (v_sim^2 / (5 - 1))
    v_sim, v_real = c**2 * 0.1 / 4 / 5, 0.175 / 4
    df = (v_sim + v_real) ** 2 / (v_sim**2 / 4)
    assert est.df == pytest.approx(df) == pytest.approx(88.24, abs=0.01)
    half = stats.t.ppf(0.975, df) * est.se
    assert (est.low, est.high) == pytest.approx((theta - half, 1.0), abs=1e-6)  # theta + half = 1.07, clipped


def test_ppi_is_the_control_variate_with_coefficient_one():
    y = np.array([1, 0, 1, 0, 1])
    f = np.array([0.1, 0.9, 0.95, 0.05, 0.6])  # rectifier spread 0.58 > mean f(1-f) = 0.0975: no floor
    sims = np.array([0.5, 0.9, 0.6, 0.7])
    est = ppi(sims, y, f)
    assert est.estimate == pytest.approx(sims.mean() + (y - f).mean())
    assert (y - f).var(ddof=1) > np.mean(f * (1 - f))
    v_sim, v_real = sims.var(ddof=1) / 4, (y - f).var(ddof=1) / 5
    assert est.se == pytest.approx(np.sqrt(v_sim + v_real))
    # the rectifier's variance is estimated from the 5 real runs: the t quantile at Welch-Satterthwaite's df
    df = (v_sim + v_real) ** 2 / (v_sim**2 / 3 + v_real**2 / 4)
    assert est.df == pytest.approx(df) == pytest.approx(4.65, abs=0.01)
    half = stats.t.ppf(0.975, df) * est.se  # about 2.7 se where the normal quantile would say 1.96
    assert (est.low, est.high) == pytest.approx((max(0.0, est.estimate - half), min(1.0, est.estimate + half)))


def test_claim_withdrawn_when_the_model_is_badly_wrong():
    # the model predicts 10 % where all ten real runs met the goal: the rectifier is 0.9 every time
    v = ppi_verdict(np.full(100, 0.1), np.ones(10), np.full(10, 0.1), p_required=0.5)
    assert v.withdrawn and v.basis == "real-only" and "withdrawn" in v.reason
    assert (v.low, v.high) == (v.real_only.low, v.real_only.high) and v.verdict is Verdict.PASS
    assert v.model_estimate.estimate == pytest.approx(1.0)  # what was refused is still shown


@pytest.mark.parametrize("n_real, slope, at_least", [(10, 4.0, 0.9), (40, 8.0, 0.95)])
def test_badly_biased_model_is_caught(n_real, slope, at_least):
    """Logit shift -5: the model predicts failure where the real runs mostly succeed. Measured withdrawal
    at 10 real runs: 96 % with slope 4, but 67 % with slope 8, where the model is wrong only for the few
    starts in the middle and 10 real runs often miss them; 40 real runs catch it."""
    rng, reps = np.random.default_rng(4), 200
    rate = np.mean(
        [
            ppi_verdict(*synthetic(rng, n_real, slope, -5.0), p_required=0.5, sims_per_start=SIMS_PER_START).withdrawn
            for _ in range(reps)
        ]
    )
    assert rate >= at_least


def test_estimated_predictions_never_make_a_point_interval():
    """3 real failures where every start's 20 simulated runs failed too: as exact probabilities the
    interval is the point 0; as estimates from 20 runs each start keeps a chance of 0.5/21 (the real
    lane-keeping x = 50 case, where all 66 real runs show 11 % success)."""
    sims, y, f = np.zeros(200), np.zeros(3), np.zeros(3)
    exact = ppi(sims, y, f)
    assert (exact.low, exact.high) == (0.0, 0.0)
    est = ppi(sims, y, f, sims_per_start=20)
    g = 0.5 / 21
    assert est.se == pytest.approx(np.sqrt(g * (1 - g) / 3)) and est.low == 0.0
    assert est.df == math.inf  # the floor, a variance from the model's runs: the normal quantile
    assert est.high == pytest.approx(1.959964 * np.sqrt(g * (1 - g) / 3), rel=1e-6)


def test_welch_degrees_of_freedom():
    assert welch_df(0.0, 200, 0.04, 10) == pytest.approx(9.0)  # one term: its own n - 1
    assert welch_df(0.01, 11, 0.01, 11) == pytest.approx(20.0)  # two equal terms: the pooled 2 (n - 1)
    assert welch_df(0.0, 5, 0.0, 5) == math.inf  # nothing estimated: the sum is known
    assert welch_df(0.01, 11, 0.05, math.inf) == pytest.approx(0.06**2 / (0.01**2 / 10))  # a known term adds none


def test_rectifier_check_values():
    chk = rectifier_check([1, 0, 1, 1], [0.5, 0.5, 0.5, 0.5], level=0.05)
    r = np.array([0.5, -0.5, 0.5, 0.5])
    assert chk.mean == pytest.approx(0.25) and chk.sd == pytest.approx(r.std(ddof=1))
    assert (chk.low, chk.high) == pytest.approx(tuple(stats.ttest_1samp(r, 0).confidence_interval(0.95)))
    # 3 of 4 under Binomial(4, 1/2): counts no likelier than 3 are 0, 1, 3, 4 -> (1 + 4 + 4 + 1) / 16
    assert chk.p_value == pytest.approx(10 / 16) and chk.passed
    exact = rectifier_check([1, 1, 1], [1.0, 1.0, 1.0])
    assert exact.mean == 0 and exact.passed and exact.p_value == 1.0


def test_calibration_test_matches_binomtest_and_shrinks_estimated_predictions():
    y = np.r_[np.ones(9), np.zeros(11)]
    assert calibration_p_value(y, np.full(20, 0.3)) == pytest.approx(stats.binomtest(9, 20, 0.3).pvalue)
    # three real successes where the model saw 0, 20 and 20 successes in 20 simulated runs
    y, f = np.array([1, 1, 1]), np.array([0.0, 1.0, 1.0])
    assert rectifier_check(y, f).p_value < 1e-12  # as exact probabilities: a count of 3 is impossible
    shrunk = rectifier_check(y, f, level=0.01, sims_per_start=20)  # as estimates from 20 runs: rare, not impossible
    assert shrunk.passed and shrunk.p_value == pytest.approx(
        (0.5 / 21) * (20.5 / 21) ** 2 + (20.5 / 21) * (0.5 / 21) ** 2
    )


def test_detectable_error_known_binomial_answer():
    """All starts at 1/2, 10 runs, level 0.05: the exact two-sided test rejects counts 0, 1, 9, 10; the
    smallest shift (in steps of 0.01) with rejection probability >= 0.8, computed here with scipy."""
    reject = [k for k in range(11) if stats.binomtest(k, 10, 0.5).pvalue <= 0.05]
    assert reject == [0, 1, 9, 10]

    def power(p: float) -> float:
        return float(sum(stats.binom.pmf(k, 10, p) for k in reject))

    want = next(d / 100 for d in range(1, 101) if power(0.5 + d / 100) >= 0.8)
    assert detectable_error(np.full(10, 0.5), 0.05) == pytest.approx((want, want))  # symmetric at 1/2
    assert 0.4 < want < 0.45  # 10 runs at P = 0.5 miss an error of 0.4 more than a fifth of the time


def test_detectable_error_shrinks_with_more_runs_and_is_none_at_the_edge():
    ten, forty = detectable_error(np.full(10, 0.5), 0.05), detectable_error(np.full(40, 0.5), 0.05)
    assert forty[0] < ten[0] and forty[1] < ten[1]
    down, up = detectable_error(np.full(10, 0.95), 0.05)
    assert up is None and down is not None  # no P above 1 to shift to; a drop is seen
    chk = rectifier_check([1, 0, 1, 1, 1, 1, 0, 1, 1, 1], np.full(10, 0.8), level=0.05)
    assert (chk.detectable_down, chk.detectable_up) == detectable_error(np.full(10, 0.8), 0.05)
    assert chk.to_json()["detectable_error"]["power"] == 0.8 and "10 runs" in chk.detectable_text
    # with margins the count test has half the level, so it needs a larger error
    sims = np.tile(np.linspace(-1, 1, 20), (10, 1))
    with_margins = rectifier_check([1] * 8 + [0] * 2, np.full(10, 0.8), 0.05, None, np.zeros(10), sims)
    assert (with_margins.detectable_down, with_margins.detectable_up) == detectable_error(np.full(10, 0.8), 0.025)


def test_model_only_carries_the_measured_error():
    sims = np.r_[np.ones(950), np.zeros(50)]
    good = rectifier_check([1, 0, 1, 1, 1, 1, 0, 1, 1, 1], [0.9, 0.3, 0.8, 0.9, 0.7, 0.8, 0.4, 0.9, 0.8, 0.9])
    v = model_only(sims, 0.8, {"x=10": good})
    lo, hi = clopper_pearson(950, 1000)
    bound = max(abs(good.low), abs(good.high))
    assert (v.low, v.high) == (lo, hi) and v.n_sim == 1000 and v.basis == "model only"
    assert v.widened_low == pytest.approx(max(0.0, lo - bound)) and v.widened_high == pytest.approx(min(1, hi + bound))
    assert "rests on the model only" in v.reason and v.to_json()["measured_errors"]["x=10"]["n"] == 10
    assert v.verdict.value == ("PASS" if v.widened_low >= 0.8 else "UNDECIDED")
    assert model_only(sims, 0.8, {}).verdict is Verdict.UNDECIDED
    bad = rectifier_check(np.ones(10), np.full(10, 0.1))
    refused = model_only(sims, 0.8, {"x=10": good, "x=50": bad})
    assert refused.verdict is Verdict.UNDECIDED and "x=50" in refused.reason
    easy = rectifier_check(np.ones(10), np.full(10, 0.99))
    assert model_only(sims, 0.5, {"x=10": easy}, left_training=(100, 1000)).verdict is Verdict.PASS  # at the limit
    beyond = model_only(sims, 0.5, {"x=10": easy}, left_training=(101, 1000))
    assert beyond.verdict is Verdict.UNDECIDED and "101 of its 1000 simulated runs leave" in beyond.reason


def test_pit_values_known_answers():
    sims = np.array([[1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0], [5.0, 5.0, 5.0, 5.0]])
    u = pit_values([10.0, 0.0, 5.0], sims, seed=3)
    assert 4 / 5 <= u[0] <= 1.0  # above all 4: the top fifth
    assert 0.0 <= u[1] <= 1 / 5  # below all 4: the bottom fifth
    assert 0.0 <= u[2] <= 1.0  # tied with all 4: anywhere, at random
    assert np.array_equal(u, pit_values([10.0, 0.0, 5.0], sims, seed=3))  # a verdict repeats
    inf = pit_values([np.inf, -np.inf], [[np.inf, 0.0], [0.0, 1.0]], seed=0)  # a metric that never settles
    assert 1 / 3 <= inf[0] <= 1.0 and inf[1] <= 1 / 3
    ties = [pit_values([5.0], [[5.0, 5.0, 5.0, 5.0]], seed=k)[0] for k in range(400)]
    assert stats.kstest(ties, "uniform").pvalue > 0.01  # ties broken uniformly


def margins_synthetic(rng: np.random.Generator, n_real: int, model_shift: float):
    """The start decides the outcome: margin = start + small noise (sd 0.2); the model adds
    ``model_shift`` to the margin. Outcomes are margin >= 0. Returns the verdict's arguments."""
    x, xs = rng.normal(size=n_real), rng.normal(size=STARTS)
    real = x + 0.2 * rng.normal(size=n_real)
    paired = x[:, None] + model_shift + 0.2 * rng.normal(size=(n_real, SIMS_PER_START))
    sims = ((xs[:, None] + model_shift + 0.2 * rng.normal(size=(STARTS, SIMS_PER_START))) >= 0).mean(axis=1)
    y = (real >= 0).astype(float)
    f = (paired >= 0).mean(axis=1)
    return sims, y, f, real, paired


def test_margin_test_keeps_a_faithful_model():
    """Real and paired margins exchangeable: both tests together withdraw at most at the level."""
    rng, reps = np.random.default_rng(7), 300
    withdrawn = []
    for k in range(reps):
        sims, y, f, real, paired = margins_synthetic(rng, 10, 0.0)
        v = ppi_verdict(
            sims, y, f, 0.5, sims_per_start=SIMS_PER_START, real_margins=real, paired_margins=paired, seed=k
        )
        withdrawn.append(v.withdrawn)
        assert v.check.margin_p_value is not None
    assert np.mean(withdrawn) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / reps)


def test_a_kept_claim_states_the_level_each_test_ran_at():
    """With the margins each test runs at half the level: a kept claim beside a p between the half and
    the whole level must not read "withdrawn at 0.05" (a reader takes that for a contradiction)."""
    rng = np.random.default_rng(11)
    between = []
    for k in range(400):
        sims, y, f, real, paired = margins_synthetic(rng, 10, 0.0)
        v = ppi_verdict(
            sims, y, f, 0.5, sims_per_start=SIMS_PER_START, real_margins=real, paired_margins=paired, seed=k
        )
        if not v.withdrawn:
            assert "each test withdraws at p <= 0.025, half of 0.05" in v.reason
            assert "withdrawn at 0.05" not in v.reason
            ps = (v.check.p_value, v.check.margin_p_value)
            between.append(any(0.025 < p <= 0.05 for p in ps))
    assert any(between)  # the case the wording is about occurred
    plain = ppi_verdict(*margins_synthetic(rng, 10, 0.0)[:3], 0.5, sims_per_start=SIMS_PER_START)
    assert plain.withdrawn or "(withdrawn at p <= 0.05)" in plain.reason


def test_margin_test_withdraws_a_model_wrong_only_where_outcomes_rarely_show_it():
    """The model's margins are 0.5 low: wrong only for starts near the threshold, which 10 real runs
    often miss, so the outcome test alone keeps the claim and the interval misses the truth (the car
    twin's badly wrong follower, benchmarks/coverage_twin.py). The margins show it in every run."""
    rng, reps, truth = np.random.default_rng(8), 200, 0.5
    kept_outcomes_only, covered_outcomes_only, withdrawn_with_margins = [], [], []
    for k in range(reps):
        sims, y, f, real, paired = margins_synthetic(rng, 10, -0.5)
        plain = ppi_verdict(sims, y, f, 0.5, sims_per_start=SIMS_PER_START)
        kept_outcomes_only.append(not plain.withdrawn)
        if not plain.withdrawn:
            covered_outcomes_only.append(plain.low <= truth <= plain.high)
        both = ppi_verdict(
            sims, y, f, 0.5, sims_per_start=SIMS_PER_START, real_margins=real, paired_margins=paired, seed=k
        )
        withdrawn_with_margins.append(both.withdrawn)
        if both.withdrawn:
            assert "PIT test" in both.reason or "calibration test" in both.reason
    assert np.mean(kept_outcomes_only) >= 0.5 and np.mean(covered_outcomes_only) < 0.93  # the failure it fixes
    assert np.mean(withdrawn_with_margins) >= 0.95


def noisy_synthetic(rng: np.random.Generator, model_noise: float):
    """Runs of 50 samples: a start level x plus white noise (sd 1 real, ``model_noise`` in the model);
    the requirement is "mean >= 0", whose margin the noise barely moves, so only the runs' roughness
    tells a model with the wrong noise from the real system. Returns the verdict's arguments and the
    traces' summaries."""
    x, xs = rng.normal(size=10), rng.normal(size=STARTS)
    real = x[:, None] + rng.normal(size=(10, 50))
    paired = x[:, None, None] + model_noise * rng.normal(size=(10, SIMS_PER_START, 50))
    further = xs[:, None, None] + model_noise * rng.normal(size=(STARTS, SIMS_PER_START, 50))
    real_m, paired_m = real.mean(axis=1), paired.mean(axis=2)
    mine, theirs = trace_summaries(real), trace_summaries(paired.reshape(-1, 50))
    summaries = {k: (v, theirs[k].reshape(10, SIMS_PER_START)) for k, v in mine.items()}
    args = ((further.mean(axis=2) >= 0).mean(axis=1), (real_m >= 0).astype(float), (paired_m >= 0).mean(axis=1))
    return args, {"real_margins": real_m, "paired_margins": paired_m, "summaries": summaries}


def test_trace_summaries():
    got = trace_summaries([[0.0, 2.0, 0.0, 2.0], [1.0, 1.0, 1.0, 4.0]])
    assert got["mean"] == pytest.approx([1.0, 1.75])
    assert got["spread"] == pytest.approx([1.0, np.std([1, 1, 1, 4])])
    assert got["roughness"] == pytest.approx([2.0, 1.0])
    with pytest.raises(ValueError, match="at least 2 samples"):
        trace_summaries([[1.0], [2.0]])


def test_run_summaries_withdraw_a_model_whose_runs_look_wrong_and_keep_a_faithful_one():
    """Noise 1.5x the real one: margins and outcomes pass the check most of the time, the roughness
    test catches it nearly always. With a faithful model the five tests together (count, margin and
    three summaries, each at level / 5) withdraw at most at the level."""
    rng, reps = np.random.default_rng(21), 200
    caught, kept_without = [], []
    for k in range(reps):
        args, extra = noisy_synthetic(rng, 1.5)
        plain = ppi_verdict(*args, 0.5, sims_per_start=SIMS_PER_START, seed=k, **{**extra, "summaries": None})
        v = ppi_verdict(*args, 0.5, sims_per_start=SIMS_PER_START, seed=k, **extra)
        kept_without.append(not plain.withdrawn)
        caught.append(v.withdrawn)
        if v.withdrawn and plain.check.passed:
            assert re.search(r"real runs' (spread|roughness) is not a plausible draw", v.reason)
    assert np.mean(kept_without) >= 0.8 and np.mean(caught) >= 0.95
    withdrawn = []
    for k in range(reps):
        args, extra = noisy_synthetic(rng, 1.0)
        v = ppi_verdict(*args, 0.5, sims_per_start=SIMS_PER_START, seed=k, **extra)
        assert v.check.tests == 5 and set(v.check.summary_p_values) == {"mean", "spread", "roughness"}
        if not v.withdrawn:
            assert "each test withdraws at p <= 0.01, 1/5 of 0.05" in v.reason
        withdrawn.append(v.withdrawn)
    assert np.mean(withdrawn) <= 0.05 + 3 * np.sqrt(0.05 * 0.95 / reps)
    assert "summary_p_values" in v.check.to_json() and "each of the 5 tests" in v.check.to_json()["test"]


def test_summaries_pair_with_the_runs():
    with pytest.raises(ValueError, match="summary 'x' must hold one value per real run"):
        rectifier_check([1, 0], [0.5, 0.5], summaries={"x": ([1.0, 2.0, 3.0], [[1.0], [2.0]])})
    with pytest.raises(ValueError, match="NaN"):
        rectifier_check([1, 0], [0.5, 0.5], summaries={"x": ([1.0, 2.0], [[1.0], [float("nan")]])})


def test_margins_go_together_and_pair_with_the_runs():
    with pytest.raises(ValueError, match="go together"):
        rectifier_check([1, 0], [0.5, 0.5], real_margins=[1.0, -1.0])
    with pytest.raises(ValueError, match=r"\(real runs, simulations\)"):
        rectifier_check([1, 0], [0.5, 0.5], real_margins=[1.0, -1.0], paired_margins=[[1.0, 2.0, 3.0]])
    with pytest.raises(ValueError, match=r"\(real runs, simulations\)"):
        rectifier_check([1, 0], [0.5, 0.5], real_margins=[1.0, -1.0], paired_margins=[1.0, 2.0])
    with pytest.raises(ValueError, match="one margin per real run"):
        rectifier_check([1, 0], [0.5, 0.5], real_margins=[1.0, -1.0, 2.0], paired_margins=[[1.0], [2.0]])
    with pytest.raises(ValueError, match="NaN"):
        rectifier_check([1, 0], [0.5, 0.5], real_margins=[1.0, -1.0], paired_margins=[[1.0], [float("nan")]])


@pytest.mark.parametrize(
    "args, match",
    [
        (([0.5, 0.5], [1, 0, 1], [0.5, 0.5]), "must pair run by run"),
        (([0.5, 0.5], [1, 0.5], [0.5, 0.5]), "goal outcomes"),
        (([0.5, float("nan")], [1, 0], [0.5, 0.5]), "sim_predictions holds 1 NaN"),
        (([0.5, 0.5], [1, 0], [0.5, 1.5]), "probabilities in"),
    ],
)
def test_bad_inputs(args, match):
    with pytest.raises(ValueError, match=match):
        ppi_verdict(*args, p_required=0.5)


def test_an_error_measured_on_runs_that_all_agree_is_not_known_exactly():
    """30 of 30 real runs met the goal where the model said they would: the rectifier has no spread,
    but 0/1 outcomes leave the real share anywhere down to 0.884 (exact interval), so the measured
    error reaches -0.116 and a version without real runs is widened by it, not by +-0."""
    check = rectifier_check(np.ones(30), np.ones(30))
    lo, _ = clopper_pearson(30, 30, 0.95)
    assert check.low == pytest.approx(lo - 1.0) and check.high == 0.0 and check.low < -0.1
    v = model_only(np.ones(1000), 0.95, {"x=30": check})
    assert v.widened_low == pytest.approx(clopper_pearson(1000, 1000, 0.95)[0] - (1.0 - lo))
    assert v.verdict is Verdict.UNDECIDED  # it was PASS on an error of +-0.000

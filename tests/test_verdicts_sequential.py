"""SPRT error rates and run counts on seeded Bernoulli streams; coverage of the confidence sequence at its stop."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.verdicts import Verdict, confidence_sequence, fixed_sample_size, mixture_interval, sprt, sprt_expected_runs

REPS = 2000


def stream(p: float, rng: np.random.Generator):
    return lambda n: rng.random(n) < p


def tolerance(rate: float, reps: int) -> float:
    return 3 * np.sqrt(rate * (1 - rate) / reps)


@pytest.mark.parametrize("p, wrong", [(0.85, Verdict.PASS), (0.95, Verdict.FAIL)])
def test_sprt_error_rates_and_runs(p, wrong):
    """At p0 = 0.85 a PASS, at p1 = 0.95 a FAIL is the error; both at most alpha = beta = 0.05."""
    rng = np.random.default_rng(11)
    results = [sprt(stream(p, rng), 0.9, delta=0.05, alpha=0.05, beta=0.05, batch=5) for _ in range(REPS)]
    errors = np.mean([r.verdict is wrong for r in results])
    assert errors <= 0.05 + tolerance(0.05, REPS)
    runs = np.array([r.runs for r in results])
    wald = sprt_expected_runs(p, 0.9, 0.05, 0.05, 0.05)
    # Wald's approximation ignores the overshoot (and batches of 5 add some): realised mean at or a bit above it
    assert 0.9 * wald <= runs.mean() <= 1.6 * wald
    n_fixed, _ = fixed_sample_size(0.9, 0.05, 0.05, 0.05)
    assert runs.mean() < 0.75 * n_fixed
    assert all(r.verdict is not Verdict.UNDECIDED for r in results)  # max_runs 10,000 is never reached here
    # the interval reported at the stop is any-time valid: it covers p at least 95 % of the time
    assert np.mean([r.low <= p <= r.high for r in results]) >= 0.95 - tolerance(0.05, REPS)


def test_sprt_far_from_the_requirement_is_quick_and_right():
    rng = np.random.default_rng(5)
    r = sprt(stream(0.5, rng), 0.9, batch=1)
    assert r.verdict is Verdict.FAIL and r.runs <= 10 and len(r.looks) == r.runs
    assert r.looks[-1].llr <= np.log(0.05 / 0.95)


def test_sprt_truncated_at_max_runs_is_undecided():
    r = sprt(lambda n: np.arange(n) % 10 != 0, 0.9, max_runs=40, batch=7)  # exactly 90 %: in the indifference zone
    assert r.verdict is Verdict.UNDECIDED and r.runs == 40 and [lk.runs for lk in r.looks] == [7, 14, 21, 28, 35, 40]


def test_fixed_sample_size_is_the_smallest_exact_design():
    from scipy import stats

    n, c = fixed_sample_size(0.9, 0.05, 0.05, 0.05)
    assert stats.binom.sf(c - 1, n, 0.85) <= 0.05 and stats.binom.cdf(c - 1, n, 0.95) <= 0.05
    for m in range(n - 20, n):  # no smaller n has any critical count meeting both error rates
        assert not any(
            stats.binom.sf(k - 1, m, 0.85) <= 0.05 and stats.binom.cdf(k - 1, m, 0.95) <= 0.05 for k in range(m + 1)
        )


def test_wald_expected_runs_at_the_hypotheses_closed_form():
    a, b = np.log(0.95 / 0.05), np.log(0.05 / 0.95)
    up, down = np.log(0.95 / 0.85), np.log(0.05 / 0.15)
    e0 = 0.85 * up + 0.15 * down
    assert sprt_expected_runs(0.85, 0.9) == pytest.approx((0.95 * b + 0.05 * a) / e0, rel=1e-6)


@pytest.mark.parametrize("method", ["mixture", "bonferroni"])
def test_confidence_sequence_covers_at_its_stopping_time(method):
    """p close to p_required keeps the procedure looking many times; coverage at the stop stays >= 95 %."""
    rng = np.random.default_rng(7)
    p, reps = 0.87, 300
    results = [confidence_sequence(stream(p, rng), 0.9, max_runs=400, batch=20, method=method) for _ in range(reps)]
    cover = np.mean([r.low <= p <= r.high for r in results])
    assert cover >= 0.95 - tolerance(0.05, reps)
    assert np.mean([r.verdict is Verdict.PASS for r in results]) <= 0.05 + tolerance(0.05, reps)
    assert max(len(r.looks) for r in results) == 20  # some ran to max_runs: many looks were taken


def test_confidence_sequence_stops_when_decided():
    rng = np.random.default_rng(1)
    r = confidence_sequence(stream(0.99, rng), 0.8, batch=10)
    assert r.verdict is Verdict.PASS and r.low >= 0.8 and r.runs < 200
    assert all(a.low <= b.low and a.high >= b.high for a, b in zip(r.looks, r.looks[1:]))  # running intersection


def test_mixture_interval_contains_the_estimate_and_shrinks():
    for k, n in ((0, 10), (3, 10), (10, 10), (300, 1000)):
        lo, hi = mixture_interval(k, n)
        assert lo <= k / n <= hi
    assert np.diff(mixture_interval(80, 100)) > np.diff(mixture_interval(800, 1000))


def test_bad_sampler_output_is_one_clear_error():
    with pytest.raises(ValueError, match="returned 3 outcomes, expected 5"):
        sprt(lambda n: np.ones(3, bool), 0.9, batch=5)
    with pytest.raises(ValueError, match="goal outcomes"):
        confidence_sequence(lambda n: np.full(n, 0.5), 0.9, batch=5)
    with pytest.raises(ValueError, match="indifference region"):
        sprt(lambda n: np.ones(n, bool), 0.97, delta=0.05)

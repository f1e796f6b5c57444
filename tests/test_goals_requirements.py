"""Requirements: metric comparisons parsed without eval, STL through rtamt, the fast path equal to rtamt."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envi_py.goals.evaluate import Runs
from envi_py.goals.requirements import MetricRequirement, StlRequirement, parse, satisfied
from envi_py.verdicts import BinomialDecision, decide
from envi_py.system import RequirementSpec, load_system

SIGNALS = ("color", "distance", "steering")


def runs_of(**signals: list[float] | np.ndarray) -> Runs:
    return Runs({k: np.atleast_2d(np.asarray(v, dtype=float)) for k, v in signals.items()}, 40.0)


def req(expr: str, kind: str = "metric") -> RequirementSpec:
    return RequirementSpec("R", expr, kind)


# ---------------------------------------------------------------------- metric requirements


def test_shipped_requirements_parse_and_evaluate() -> None:
    system = load_system("car")
    runs = runs_of(color=[[40, 70, 40], [40, 80, 40]], distance=[[30, 12, 30], [30, 9, 30]])
    results = {r.name: satisfied(r, runs).tolist() for r in system.requirements}
    assert results == {"no collision": [True, False], "keeps the lane": [True, False]}


def test_metric_requirement_fields_and_flipped_comparison() -> None:
    r = parse(req("max_abs_dev(color, 40) <= 35"), SIGNALS)
    assert r == MetricRequirement("R", "max_abs_dev", "color", {"setpoint": 40.0}, "<=", 35.0)
    assert parse(req("10 <= min(distance)"), SIGNALS) == MetricRequirement("R", "min", "distance", {}, ">=", 10.0)
    kw = parse(req("time_in_band(color, band=10, setpoint=-40) > 0.5"), SIGNALS)
    assert kw.params == {"band": 10.0, "setpoint": -40.0} and kw.op == ">"


def test_strict_and_non_strict_thresholds_differ_on_the_boundary() -> None:
    runs = runs_of(distance=[[10, 12], [9, 12]])
    assert satisfied(req("min(distance) >= 10"), runs).tolist() == [True, False]
    assert satisfied(req("min(distance) > 10"), runs).tolist() == [False, False]
    assert parse(req("min(distance) >= 10"), ["distance"]).margin(runs).tolist() == [0.0, -1.0]


@pytest.mark.parametrize(
    ("expr", "message"),
    [
        ("max_abs_dev(color, 40) <=", "is not an expression"),
        ("max_abs_dev(color, 40)", "needs one comparison"),
        ("0 < min(color) < 5", "needs one comparison"),
        ("min(color) == 3", "bad operator '=='"),
        ("min(color) != 3", "bad operator '!='"),
        ("foo(color) <= 3", "unknown metric 'foo'"),
        ("min(colour) <= 3", "unknown signal 'colour'"),
        ("min(color) <= x", "threshold must be a finite number, not 'x'"),
        ("min(color) <= '3'", "threshold must be a finite number"),
        ("min(color) <= True", "threshold must be a finite number"),
        ("min(color) <= 1e999", "threshold must be a finite number"),
        ("max_abs_dev(color) <= 3", "needs parameter 'setpoint'"),
        ("max_abs_dev(color, 'a') <= 3", "parameter 'setpoint' must be a finite number"),
        ("max_abs_dev(color, 1, 2) <= 3", "takes at most 1 parameter"),
        ("max_abs_dev(color, 1, band=2) <= 3", "has no parameter 'band'"),
        ("max_abs_dev(color, 1, setpoint=2) <= 3", "'setpoint' is given twice"),
        ("max_abs_dev(40) <= 3", "needs a signal name first"),
        ("os.system(color) <= 3", "is not a metric name"),
        ("3 <= 4", "one side must be a metric call"),
    ],
)
def test_malformed_metric_requirements_are_value_errors_naming_the_requirement(expr: str, message: str) -> None:
    with pytest.raises(ValueError, match=f"requirement 'R': .*{message}"):
        parse(req(expr), SIGNALS)


# ---------------------------------------------------------------------- STL requirements


@pytest.mark.parametrize(
    ("expr", "message"),
    [
        ("always[0:10](color >", "STL syntax error"),
        ("always[0:10](color >= 5", "STL syntax error"),
        ("always[0:10](colour >= 5)", "unknown signal 'colour'"),
        ("always[0:1s](color >= 5)", "has a unit"),
        ("always[0:2.5](color >= 5)", "whole numbers of samples"),
        ("always[5:2](color >= 5)", "is empty"),
        ("color + 3", "not a condition"),
        ("always(1 > 0)", "reads no signal"),
    ],
)
def test_malformed_stl_requirements_are_value_errors(expr: str, message: str) -> None:
    with pytest.raises(ValueError, match=f"requirement 'R': .*{message}"):
        parse(req(expr, "stl"), SIGNALS)


def test_unknown_kind_is_an_error() -> None:
    with pytest.raises(ValueError, match="kind must be 'metric' or 'stl'"):
        parse(RequirementSpec("R", "min(color) > 1", "ltl"), SIGNALS)


def test_always_holds_unless_the_signal_leaves_the_band_within_the_bound() -> None:
    t = 120
    base = np.full(t, 50.0)
    dip_inside, dip_after, peak = base.copy(), base.copy(), base.copy()
    dip_inside[50] = 3.0  # within [0:100]: violated
    dip_after[110] = 3.0  # after the bound: not looked at
    peak[100] = 96.0  # on the bound's last sample: violated
    runs = runs_of(color=np.stack([base, dip_inside, dip_after, peak]))
    r = parse(req("always[0:100](color >= 5 and color <= 95)", "stl"), ["color"])
    assert isinstance(r, StlRequirement) and r.fast is not None
    assert r.satisfied(runs).tolist() == [True, False, True, False]
    assert r.robustness(runs, use_fast=False).tolist() == [45.0, -2.0, 45.0, -1.0]


def test_eventually_needs_one_sample_in_the_window() -> None:
    t = 60
    far = np.full((3, t), 80.0)
    far[1, 20] = 35.0  # reaches the lead within [10:30]
    far[2, 40] = 35.0  # too late
    runs = runs_of(distance=far)
    assert satisfied(req("eventually[10:30](distance <= 40)", "stl"), runs).tolist() == [False, True, False]


def test_stl_starts_after_the_skipped_rows() -> None:
    color = np.full((1, 30), 50.0)
    color[0, 2] = 0.0
    runs = Runs({"color": color}, 40.0, skip=5)
    assert satisfied(req("always(color >= 5)", "stl"), runs).tolist() == [True]
    assert satisfied(req("always(color >= 5)", "stl"), Runs({"color": color}, 40.0, skip=0)).tolist() == [False]


def test_nested_formula_uses_rtamt() -> None:
    r = parse(req("always[0:1](eventually[0:1](color >= 2))", "stl"), ["color"])
    assert r.fast is None
    assert r.robustness(runs_of(color=[[3, 1, 1, 5], [3, 3, 1, 5]])).tolist() == [-1.0, 1.0]


FAST_FORMS = [
    "always[0:100](color >= 5 and color <= 95)",
    "always(color > 20)",
    "eventually[5:40](distance < 30)",
    "eventually(distance <= 10 or color >= 90)",
    "always[10:20](not color > 80)",
    "always[0:30](abs(color - 40) <= 25)",
    "always[0:50](color - 2 * steering >= -30 and (distance > 5 or not steering < 0))",
    "eventually[0:500](color > 95)",  # bound beyond the run: cut at its end
    "always[200:300](color > 95)",  # window beyond the run: vacuously true
    "eventually[200:300](color > 95)",  # ... and vacuously false
    "color >= 40 and distance < 50",  # no temporal operator: time 0
    "30 < color",
]


@pytest.mark.parametrize("expr", FAST_FORMS)
def test_fast_path_equals_rtamt(expr: str) -> None:
    rng = np.random.default_rng(zlib.crc32(expr.encode()))
    n, t = 40, 110
    runs = runs_of(
        color=50 + 40 * np.sin(np.arange(t) / 5 + rng.uniform(0, 6, (n, 1))) + rng.normal(0, 5, (n, t)),
        distance=rng.uniform(0, 100, (n, t)),
        steering=rng.normal(0, 10, (n, t)),
    )
    r = parse(req(expr, "stl"), SIGNALS)
    assert r.fast is not None
    fast, slow = r.robustness(runs), r.robustness(runs, use_fast=False)
    assert np.array_equal(np.isinf(fast), np.isinf(slow))
    assert np.allclose(fast, slow, atol=1e-9)
    assert np.isinf(slow).all() or np.ptp(slow) > 0  # the runs differ: the comparison is not trivial


def test_stl_needs_two_samples() -> None:
    with pytest.raises(ValueError, match="at least 2 scored samples"):
        satisfied(req("always(color > 1)", "stl"), runs_of(color=[[5.0]]))


# ---------------------------------------------------------------------- verdicts with their probability


def _decision(distance: np.ndarray, p: float = 0.9) -> BinomialDecision:
    ok = satisfied(RequirementSpec("no collision", "min(distance) >= 10", probability=p), runs_of(distance=distance))
    return decide(int(ok.sum()), ok.size, p)


@pytest.mark.parametrize(("passing", "n", "word"), [(200, 200, "PASS"), (150, 200, "FAIL"), (18, 20, "UNDECIDED")])
def test_requirement_outcomes_decide_with_the_exact_interval(passing: int, n: int, word: str) -> None:
    distance = np.full((n, 5), 30.0)
    distance[passing:, 2] = 5.0
    v = _decision(distance)
    assert (v.k, v.n, v.verdict.value) == (passing, n, word)
    assert v.low <= v.p_hat <= v.high


def test_requirement_interval_is_clopper_pearson() -> None:
    # 18 of 20: the exact 95% interval is [0.683, 0.988] (Clopper and Pearson 1934, tabulated)
    distance = np.full((20, 5), 30.0)
    distance[18:, 0] = 0.0
    v = _decision(distance)
    assert v.low == pytest.approx(0.6830, abs=5e-4) and v.high == pytest.approx(0.9877, abs=5e-4)


def test_runs_without_the_formulas_signal_name_the_requirement() -> None:
    r = parse(req("always(distance > 1)", "stl"), SIGNALS)
    with pytest.raises(ValueError, match="requirement 'R': unknown signal 'distance'"):
        r.satisfied(runs_of(color=[[1.0, 2.0]]))


@settings(max_examples=60, deadline=None)
@given(
    op=st.sampled_from(["always", "eventually"]),
    lo=st.integers(0, 30),
    width=st.integers(0, 30),
    threshold=st.floats(-50, 50),
    cmp=st.sampled_from([">=", ">", "<=", "<"]),
    values=st.lists(st.floats(-100, 100), min_size=2, max_size=40),
)
def test_fast_path_equals_rtamt_on_any_bound_and_trace(
    op: str, lo: int, width: int, threshold: float, cmp: str, values: list[float]
) -> None:
    r = parse(req(f"{op}[{lo}:{lo + width}](color {cmp} {threshold!r})", "stl"), ["color"])
    runs = runs_of(color=[values, values[::-1]])
    assert r.fast is not None
    assert np.array_equal(r.robustness(runs), r.robustness(runs, use_fast=False))

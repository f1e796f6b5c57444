"""What the diagnosis says and draws: a floor of 0, the gap gate, one number per concept, figures
readable for five versions, a horizon that is blind to the phase of an oscillating robot."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.patches import Rectangle

from envi_py.diagnose.effects import Finding
from envi_py.diagnose.gap import floor_ratio, gap_test, horizon_gap, oscillation_rows, ratio_text, share_text
from envi_py.diagnose.report import _candidates_section, horizon_figure, metrics_figure, residual_map_figure
from envi_py.diagnose.run import Diagnosis, significant_gap

VERSIONS = [f"x={x}" for x in (10, 20, 30, 40, 50)]


def _row(goal: str, ratio: float, p: float, floor: float = 0.02) -> dict:
    w1 = ratio * floor if np.isfinite(ratio) else 0.03
    return {
        "goal": goal,
        "signal": "color",
        "unit": "%",
        "scale": 100.0,
        "w1": w1,
        "floor": floor if np.isfinite(ratio) else 0.0,
        "ratio": ratio,
        "ratio_null_band": [0.5, 2.5],
        "p": p,
        "beyond_floor": p <= 0.05,
        "w1_all": w1,
        "ci": [w1 / 2, w1 * 2],
        "real": [1.0, 2.0, 3.0, 4.0],
        "sim": [1.5, 2.5, 3.5, 4.5],
    }


def _diagnosis(version_p: float, ratios=(3.0, 1.2), findings=()) -> Diagnosis:
    gaps = [
        {
            "controller": v,
            "gaps": [
                _row("over_count", ratios[0], 0.01 if version_p < 0.05 else 0.4),
                _row("steady_count", ratios[1], 0.5),
            ],
            "n_real": 4,
            "n_sim": 8,
            "per_side": 2,
            "mean_w1": 0.04,
            "mean_floor": 0.02,
            "goals_test": {"p_value": version_p},
        }
        for v in VERSIONS
    ]
    horizon = [
        {
            "controller": v,
            "signal": "color",
            "unit": "%",
            "step": [10, 11, 12],
            "width": 10,
            "ratio": [0.9, 1.4, 1.6],
            "median_ratio": 1.4,
            "above_from_step": 11,
        }
        for v in VERSIONS
    ]
    test = significant_gap(gaps)
    d = Diagnosis(list(findings), gaps, horizon, [], [], {"outside_share": 0.0031}, None, gap_test=test)
    return d


def test_a_floor_of_zero_is_said_as_such_never_as_a_huge_ratio():
    assert floor_ratio(0.0278, 0.0) == float("inf") and floor_ratio(0.0, 0.0) == 0.0
    assert ratio_text(floor_ratio(0.0278, 0.0)) == "floor 0: any difference is a gap"
    d = _diagnosis(0.001, ratios=(float("inf"), 1.2))
    assert "over_count of x=10 (floor 0: any difference is a gap; normalised W1 0.0300" in d.verdict()
    assert "e+" not in d.verdict() and "555" not in d.verdict()


def test_within_the_floor_is_no_significant_gap_and_nothing_is_attributed():
    d = _diagnosis(0.3)
    assert not d.gap_test["significant"] and d.no_gap
    assert "No significant gap: every controller version's goals are within the real-vs-real floor" in d.verdict()
    # Holm over versions: five versions at p = 0.02 each are not a gap at 5% (the smallest adjusted is 0.1)
    assert not gap_test([{"controller": v, "goals_test": {"p_value": 0.02}} for v in VERSIONS])["significant"]
    assert gap_test([{"controller": v, "goals_test": {"p_value": 0.005}} for v in VERSIONS])["significant"]


def test_a_gap_no_candidate_explains_is_none_of_the_candidates():
    quiet = Finding("noise", 1.0, 0.5, 0.0, "color scatters by sd 0.2 %", {}, p_holm=1.0)
    d = _diagnosis(0.001, findings=[quiet])
    assert d.gap_test["significant"] and "None of the candidates explains the gap" in d.verdict()


def test_the_held_out_share_is_shown_where_it_was_counted():
    """The candidate table gives each share's held-out counterpart only when the logs fit
    significantly and clearly worse than the held-out logs, which is when it was counted."""
    memory = Finding("memory_delay", 9.0, 1e-9, 0.06, "rows before", {}, p_holm=1e-8, held_out=0.05)
    held = {"rms_ratio": 2.0, "p": 0.001, "worse": True, "n_logs": 20, "n_held_out": 5}

    def rows(held_out):
        d = _diagnosis(0.001, findings=[memory])
        d.held_out = held_out
        return _candidates_section(d).blocks[1].rows

    assert rows(held)[0][3:5] == ["6.0%", "5.0%"] and memory.excess == pytest.approx(0.01)
    assert rows({**held, "rms_ratio": 1.2})[0][4] == "-" and rows(None)[0][4] == "-"


def test_one_number_per_concept():
    d = _diagnosis(0.001)
    assert share_text(0.0031) == "0.3%" and share_text(0.54) == "54%"
    # coverage: the verdict and the coverage line print the same figure
    assert "0.3% of simulated windows lie outside the training data" in d.verdict()
    # the verdict's ratio is the table's
    assert "(3.0x; normalised W1" in d.verdict() and ratio_text(3.0) == "3.0x"


def test_metrics_figure_shows_every_version():
    fig = metrics_figure(_diagnosis(0.001))
    panels = [ax for ax in fig.axes if ax.get_visible() and ax.axison]
    assert len(panels) == 2
    for ax in panels:
        labels = [t.get_text().split("\n")[0] for t in ax.get_xticklabels()]
        assert labels == VERSIONS
        assert len(ax.patches) == 2 * len(VERSIONS)  # a real and a simulated box per version


def test_residual_map_shows_an_empty_cell_as_empty_not_as_zero_bias():
    mean = [[1.0, np.nan], [np.nan, -2.0]]
    d = _diagnosis(0.001)
    d.residual_map = [
        {
            "signal": "color",
            "unit": "%",
            "by_action": [
                {"mean": mean, "state_edges": [0.0, 50.0, 100.0], "actions": ["-10", "10"], "action_signal": "angle"}
            ],
        }
    ]
    fig = residual_map_figure(d)
    ax = fig.axes[0]
    shown = ax.images[0].get_array()
    assert list(np.ma.getmaskarray(shown).ravel()) == [False, True, True, False]
    assert any(isinstance(p, Rectangle) and p.get_hatch() for p in ax.patches)


def test_horizon_figure_has_one_line_per_version_and_the_floor():
    fig = horizon_figure(_diagnosis(0.001))
    assert len(fig.axes[0].get_lines()) == len(VERSIONS) + 1


def _oscillations(runs: int, steps: int, period: float, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    t = np.arange(steps)
    phase = rng.uniform(0, 2 * np.pi, (runs, 1))
    return 50 + amplitude * np.sin(2 * np.pi * t / period + phase) + rng.normal(0, 1.0, (runs, steps))


def test_horizon_gap_is_blind_to_phase_and_sees_a_wrong_amplitude():
    rng = np.random.default_rng(0)
    real = _oscillations(20, 90, 12.0, 10.0, rng)
    assert abs(oscillation_rows(real) - 12) <= 1
    same = horizon_gap(real, _oscillations(40, 90, 12.0, 10.0, rng), skip=0, seed=0)
    assert same["median_ratio"] < 1.5
    # two and a half times the real amplitude: beyond the floor from the first window on
    wide = horizon_gap(real, _oscillations(40, 90, 12.0, 25.0, rng), skip=0, seed=0)
    assert wide["median_ratio"] > 3.0 and wide["above_from_step"] == wide["step"][0]
    assert same["width"] == wide["width"] == oscillation_rows(real)


@pytest.mark.parametrize("versions", [1, 5])
def test_significant_gap_needs_a_goal_beyond_its_floor(versions):
    rows = [
        {"controller": f"v{i}", "gaps": [{"ratio": 0.8}], "goals_test": {"p_value": 0.001}} for i in range(versions)
    ]
    assert not significant_gap(rows)["significant"]

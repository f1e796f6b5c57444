"""The model-selection score: faithful simulations score below shifted or diverged ones; divergence is flagged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from envi_py.goals.evaluate import Runs
from envi_py.goals.selection import default_goals, diverged_fraction, runaway_states, selection_score
from envi_py.system import GoalSpec, load_system

CAR = load_system("car")
T = 110


def car_runs(rng: np.random.Generator, n: int = 40, shift: float = 0.0, runaway: int = 0, lead_gone: int = 0) -> Runs:
    """Colour oscillating around 40 (+shift), distance around 30; ``runaway`` runs stick at colour 100
    from sample 60; ``lead_gone`` runs read the ultrasonic maximum 255 from sample 50."""
    color = 40 + 10 * np.sin(np.arange(T) / 4 + rng.uniform(0, 6, (n, 1))) + rng.normal(0, 3, (n, T)) + shift
    distance = 30 + rng.normal(0, 5, (n, T))
    color[:runaway, 60:] = 100.0
    distance[:lead_gone, 50:] = 255.0
    return Runs({"color": np.clip(color, 0, 100), "distance": np.clip(distance, 0, 255)}, 40.0, skip=10)


def versions(rng: np.random.Generator, **kw: float) -> dict[float, Runs]:
    return {1.5: car_runs(rng, **kw), 2.5: car_runs(rng, **kw)}


@pytest.mark.parametrize("goals", [(), CAR.goals], ids=["default goals", "declared goals"])
def test_faithful_simulation_scores_below_a_shifted_one(goals) -> None:
    rng = np.random.default_rng(0)
    real = versions(rng)
    faithful = selection_score(real, versions(rng), CAR.schema, goals)
    shifted = selection_score(real, versions(rng, shift=4.0), CAR.schema, goals)
    assert not faithful.diverged and not shifted.diverged
    assert faithful.score < shifted.score
    assert faithful.real_runs == faithful.sim_runs == 80


def test_diverged_simulation_is_flagged_and_never_selected() -> None:
    rng = np.random.default_rng(1)
    real = versions(rng)
    diverged = selection_score(real, versions(rng, runaway=8), CAR.schema)
    assert diverged.diverged and diverged.score == math.inf
    assert diverged.sim_divergence == pytest.approx(0.2) and diverged.real_divergence == 0.0
    assert math.isfinite(diverged.distance)
    faithful = selection_score(real, versions(rng), CAR.schema)
    assert faithful.score < diverged.score and faithful.distance < diverged.distance


def test_a_saturating_sensor_that_saturates_in_reality_too_is_not_divergence() -> None:
    rng = np.random.default_rng(2)
    real = versions(rng, lead_gone=6)
    sim = versions(rng, lead_gone=6)
    score = selection_score(real, sim, CAR.schema)
    assert score.real_divergence == pytest.approx(0.15) and score.sim_divergence == pytest.approx(0.15)
    assert not score.diverged and math.isfinite(score.score)
    # ... but far more often than in reality is
    assert selection_score(real, versions(rng, lead_gone=20), CAR.schema).diverged


def test_default_goals_cover_every_state_from_its_mid_range() -> None:
    goals = default_goals(CAR.schema, {})
    assert [(g.metric, g.signal) for g in goals] == [
        ("mean", "color"),
        ("std", "color"),
        ("max_abs_dev", "color"),
        ("mean", "distance"),
        ("std", "distance"),
        ("max_abs_dev", "distance"),
    ]
    assert goals[2].params == {"setpoint": 50.0} and goals[5].params == {"setpoint": 127.5}


def test_the_score_is_the_mean_normalised_w1() -> None:
    rng = np.random.default_rng(4)
    real = {0: car_runs(rng)}
    sim = {0: Runs({k: v + (5.0 if k == "color" else 0.0) for k, v in real[0].signals.items()}, 40.0, 10)}
    goals = [g for g in CAR.goals if g.name == "lane deviation"][:1]
    # shifting every colour sample by +5 moves max |c - 40| by at most 5; the scale is the range width 100
    score = selection_score(real, sim, CAR.schema, goals)
    assert 0 < score.score <= 5.0 / 100 and score.per_goal == {"lane deviation": score.score}


def test_mismatched_versions_are_an_error() -> None:
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match="same controller versions"):
        selection_score({1: car_runs(rng)}, {2: car_runs(rng)}, CAR.schema)


def test_bad_goals_and_observed_ranges_are_errors() -> None:
    rng = np.random.default_rng(6)
    real, sim = {1: car_runs(rng)}, {1: car_runs(rng)}
    with pytest.raises(ValueError, match="lack state\\(s\\) distance"):
        selection_score(real, sim, CAR.schema, observed={"color": (0.0, 100.0)})
    with pytest.raises(ValueError, match="share a name"):
        selection_score(real, sim, CAR.schema, (CAR.goals[0], CAR.goals[0]))
    with pytest.raises(ValueError, match="does not declare"):
        selection_score(real, sim, CAR.schema, (GoalSpec("g", "min", "nowhere"),))


def test_runaway_states_spare_the_no_echo_reading_and_catch_a_collapse_onto_the_clamp():
    """The car's distance: holding 255 (no echo) is what real runs do, a collapse onto the 12 cm clamp
    is what they never do; the declared-range rule sees it the other way round."""
    car = load_system("car")
    states = car.schema.states
    observed = {"color": (5.0, 95.0), "distance": (12.0, 255.0)}
    clamp = [(5.0, 95.0), (12.0, 255.0)]
    t = 50
    color = np.full((3, t), 40.0)
    distance = np.vstack([np.full(t, 24.0), np.full(t, 255.0), np.full(t, 12.0)])  # fine, no echo, collapsed
    runs = Runs({"color": color, "distance": distance}, 40.0)
    one = [Runs({k: v[i : i + 1] for k, v in runs.signals.items()}, 40.0) for i in range(3)]
    declared = [diverged_fraction([r], states, observed, None, 0.05) for r in one]
    assert declared == [0.0, 1.0, 0.0]  # flags the sensor's legitimate reading, misses the collapse
    runaway = runaway_states(states, clamp, [(1, 255.0)])
    assert runaway[1].high == math.inf and runaway[1].low == 12.0 and runaway[0].low == 5.0
    assert [diverged_fraction([r], runaway, observed, None, 0.05) for r in one] == [0.0, 0.0, 1.0]
    # a sensor saturating at its low end is spared there instead
    assert runaway_states(states, clamp, [(1, 12.0)])[1].low == -math.inf


def test_selection_with_the_clamp_limits_flags_a_distance_collapsed_onto_its_clamp():
    """What closed-loop selection scores a car model with (``divergence_limits``): runs whose distance
    rests on the 12 cm clamp make the epoch diverged, which the declared ranges never did, while runs
    holding the no-echo 255 as real ones do stay fine."""
    from envi_py.train.bc import train_bc
    from envi_py.train.common import divergence_limits
    from envi_py.twin.car import generate_car_versions

    ckpt = train_bc(generate_car_versions(6, seed=5, versions=[0, 2]), epochs=1, seed=0, hidden=(8,))
    assert ckpt.config.limit_events == ((1, 255.0),)
    limits = divergence_limits(ckpt)
    low = float(ckpt.limits()[0][1])
    assert limits[1].low == low and limits[1].high == math.inf and limits[0] == ckpt.schema.states[0]
    rng = np.random.default_rng(4)
    real = versions(rng, lead_gone=4)
    collapsed = versions(rng, lead_gone=4)
    for runs in collapsed.values():
        runs.signals["distance"][:10, 40:] = low  # a quarter of the runs collapse onto the clamp
    observed = {"color": (0.0, 100.0), "distance": (low, 255.0)}
    assert not selection_score(real, collapsed, CAR.schema, observed=observed).diverged
    flagged = selection_score(real, collapsed, CAR.schema, observed=observed, limits=limits)
    assert flagged.diverged and flagged.sim_divergence == pytest.approx(0.25) and flagged.real_divergence == 0.0
    assert not selection_score(real, versions(rng, lead_gone=4), CAR.schema, observed=observed, limits=limits).diverged

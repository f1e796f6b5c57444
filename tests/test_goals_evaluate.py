"""The lane-keeping preset against the paper's metrics on the real logs, runs by signal name, goal tables."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec
from envi_py.goals.evaluate import Runs, goal_scale, goal_table, goal_unit, signals_of
from envi_py.goals.presets import goals_of, preset_goals
from envi_py.logs import LANE_KEEPING_SCHEMA, Log, LogMeta
from envi_py.metrics import METRIC_NAMES, MetricConfig, driving_metrics, metric_bounds
from envi_py.system import GoalSpec, LogSchema, load_system


def test_lane_keeping_preset_equals_the_papers_metrics_on_the_real_logs(real_logs) -> None:
    runs = signals_of(real_logs, LANE_KEEPING_SCHEMA, skip=10)
    table = goal_table(goals_of(load_system("lane-keeping")), runs)
    expected = driving_metrics(runs.signals["color"], MetricConfig())  # centre 40, band 10, skip 10
    assert list(table) == list(METRIC_NAMES)
    assert runs.count == len(real_logs) and runs.count > 10
    for j, name in enumerate(METRIC_NAMES):
        assert np.array_equal(table[name], expected[:, j]), name


def test_preset_scales_are_the_papers_bounds() -> None:
    goals = preset_goals("lane-keeping")
    _, hi = metric_bounds(90, MetricConfig())
    assert [goal_scale(g, 0, 100, 90, 40.0) for g in goals] == hi.tolist()
    assert goal_unit(goals[3], "%") == "%" and goal_unit(goals[1], "%") == "samples" and goal_unit(goals[0], "%") == ""


def test_preset_centre_follows_the_controller_threshold() -> None:
    system = replace(load_system("lane-keeping"), controller=ControllerSpec("lane-keeping", {"threshold": 45}))
    assert {g.params["centre"] for g in goals_of(system)} == {45.0}
    c = np.array([[45.0, 45, 60, 45]])
    runs = Runs({"color": c, "angle": np.zeros_like(c)}, 40.0)
    table = goal_table(goals_of(system), runs)
    assert table["over_count"].tolist() == [1.0] and table["steady_count"].tolist() == [2.0]


def test_unknown_preset_and_duplicate_goal_names_are_errors() -> None:
    with pytest.raises(ValueError, match="unknown goals preset 'nope'"):
        preset_goals("nope")
    system = load_system("lane-keeping")
    system = replace(system, goals=(GoalSpec("over_count", "max", "color"),))
    with pytest.raises(ValueError, match="goal name 'over_count' is used twice"):
        goals_of(system)
    with pytest.raises(ValueError, match="scores the signal 'color', which this system does not declare"):
        light = LogSchema((replace(LANE_KEEPING_SCHEMA.states[0], name="light"),), LANE_KEEPING_SCHEMA.actions)
        preset_goals("lane-keeping", replace(system, schema=light))


def car_log(n: int, period: float = 40.0, offset: float = 0.0) -> Log:
    schema = load_system("car").schema
    t = np.arange(n)
    states = np.stack([40 + t + offset, 100 - t], axis=1).astype(float)
    actions = np.stack([np.zeros(n), np.full(n, 300.0)], axis=1)
    logged = np.tile(np.arange(6.0), (n, 1))
    return Log(None, t * period, states, actions, LogMeta(schema=schema, period_ms=period), logged)


def test_signals_of_names_every_column_and_cuts_to_the_shortest() -> None:
    schema = load_system("car").schema
    runs = signals_of([car_log(30), car_log(25, offset=1.0)], schema, skip=5)
    assert list(runs.signals) == [
        "color",
        "distance",
        "steering",
        "speed",
        "steer_p",
        "steer_i",
        "steer_d",
        "speed_p",
        "speed_i",
        "speed_d",
    ]
    assert runs.signals["color"].shape == (2, 25) and runs.period_ms == 40.0 and runs.scored_length == 20
    assert runs.signals["color"][1, 0] == 41.0 and runs.signals["speed_d"][0, 3] == 5.0
    table = goal_table(load_system("car").goals, runs)
    assert table["closest approach"].tolist() == [76.0, 76.0]  # distance 100 - t, t = 5..24
    assert table["lane deviation"].tolist() == [24.0, 25.0]  # color 40 + t (+1), t = 5..24


def test_signals_of_refuses_logs_that_do_not_fit_the_schema() -> None:
    with pytest.raises(ValueError, match="the schema declares 1, 1, 0"):
        signals_of([car_log(10)], LANE_KEEPING_SCHEMA, skip=0)
    with pytest.raises(ValueError, match="different periods"):
        signals_of([car_log(10), car_log(10, period=50.0)], load_system("car").schema, skip=0)


def test_goal_errors_name_the_goal() -> None:
    runs = Runs({"color": np.zeros((2, 10))}, 40.0, skip=2)
    with pytest.raises(ValueError, match="goal 'g': unknown signal 'distance'"):
        goal_table([GoalSpec("g", "min", "distance")], runs)
    with pytest.raises(ValueError, match="goal 'h': metric 'iae' needs parameter 'setpoint'"):
        goal_table([GoalSpec("h", "iae", "color")], runs)


@pytest.mark.parametrize(
    ("signals", "period", "skip", "message"),
    [
        ({}, 40.0, 0, "no signals"),
        ({"a": np.zeros((2, 5)), "b": np.zeros((2, 6))}, 40.0, 0, "one shape"),
        ({"a": np.zeros((2, 5))}, 0.0, 0, "period_ms must be a positive number"),
        ({"a": np.zeros((2, 5))}, 40.0, 5, "leaves nothing to score"),
        ({"a": np.array([[0.0, np.nan]])}, 40.0, 0, "signal 'a' holds NaN"),
    ],
)
def test_bad_runs_are_refused(signals: dict, period: float, skip: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Runs(signals, period, skip)

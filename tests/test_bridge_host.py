"""Host helpers: gap and period statistics, durations, model loading, fault specs."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from firmware_bridge.host.collect import parse_duration
from firmware_bridge.host.faults import FaultSpec
from firmware_bridge.host.inject import CallableModel, WorldModel, load_model
from firmware_bridge.host.stats import gaps, period_stats
from firmware_bridge.host.world import BLACK, WHITE, EdgeWorld


def test_gaps_list_missing_tick_ranges() -> None:
    assert gaps([0, 1, 2, 3], 4) == []
    assert gaps([1, 2, 5, 9], 12) == [[0, 0], [3, 4], [6, 8], [10, 11]]
    assert gaps([], 3) == [[0, 2]]


def test_period_stats_ignore_gaps() -> None:
    s = period_stats([0, 1, 2, 5, 6], [0, 40, 81, 200, 240])
    assert s is not None and s["n"] == 3 and s["max"] == 41 and s["mean"] == pytest.approx(40.333, abs=1e-3)
    assert s["rate_hz"] == pytest.approx(1000 / 40.333, abs=1e-2)
    assert period_stats([3], [0]) is None


@pytest.mark.parametrize("text,seconds", [("4s", 4.0), ("4000ms", 4.0), ("1.5min", 90.0), ("2", 2.0)])
def test_durations(text: str, seconds: float) -> None:
    assert parse_duration(text) == pytest.approx(seconds)


def test_bad_duration() -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        parse_duration("four seconds")


def edge_colour(window: np.ndarray) -> float:
    return 75.0 if window[-1, 1] < 0 else 5.0


def test_load_model_by_import_path() -> None:
    fn = load_model("tests.test_bridge_host:edge_colour")
    assert isinstance(fn, CallableModel) and fn.history == 1
    assert fn(np.array([[40.0, -30.0]])) == 75.0
    world = load_model("firmware_bridge.host.inject:WorldModel")
    assert isinstance(world, WorldModel)
    world.reset()
    first = [world(np.array([[50.0, 0.0]])) for _ in range(3)]
    world.reset()
    assert [world(np.array([[50.0, 0.0]])) for _ in range(3)] == first  # a run repeats after reset


def test_load_model_missing_file() -> None:
    with pytest.raises(ValueError, match="no such model file"):
        load_model("/nonexistent/model.pt")


def test_fault_spec() -> None:
    spec = FaultSpec.parse("garbage=0.1, drop=0.05,disconnect=300,seed=4")
    assert (spec.garbage, spec.drop, spec.flip, spec.disconnect, spec.seed) == (0.1, 0.05, 0.0, 300, 4)
    with pytest.raises(ValueError, match="expected one of"):
        FaultSpec.parse("explode=1")


def test_stand_in_world_crosses_the_edge_under_lane_keeping() -> None:
    w = EdgeWorld(seed=3)
    colours = []
    for _ in range(200):
        c = w.read_color()
        colours.append(c)
        w.apply(30.0 if c > 40 else -30.0, 0.04)
    c = np.array(colours)
    assert BLACK - 5 <= c.min() and c.max() <= WHITE + 5
    crossings = np.sum(np.diff(np.sign(c - 40)) != 0)
    assert crossings >= 10  # it oscillates about the edge, as the real robot does


def test_brick_sim_registers_as_a_subcommand() -> None:
    from firmware_bridge.host import brick_sim

    parser = argparse.ArgumentParser(prog="envi")
    brick_sim.register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["brick-sim", "--link", "/tmp/x", "--faults", "drop=0.1", "--period", "20"])
    assert args.func is brick_sim.run_args
    assert (str(args.link), args.faults.drop, args.period, args.x) == ("/tmp/x", 0.1, 20, 30.0)

"""The second world family: a differential-drive robot on a curved track, same log schema as the
first twin, every shared effect and the two novel ones."""

from __future__ import annotations

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec
from envi_py.twin.diffdrive import NOVEL, generate_diffdrive, resemblance, resemblance_table, resolve_diffdrive
from envi_py.twin.effects import EFFECTS

LANE = ControllerSpec("lane-keeping", {"x": 30})


def _color(effects=None, seed=0, runs=8, controller=LANE):
    return np.stack([lg.states[:, 0] for lg in generate_diffdrive(controller, runs, 100, effects, seed=seed)])


def test_logs_have_the_lane_keeping_schema_integer_colours_and_record_the_world():
    logs = generate_diffdrive(LANE, 3, 50, {"noise": 2.0}, seed=1)
    lg = logs[0]
    assert list(lg.meta.schema.columns) == ["time", "color", "angle"] and len(lg) == 50
    assert np.all(lg.states == np.round(lg.states)) and lg.states.min() >= 0 and lg.states.max() <= 100
    assert set(np.unique(lg.actions)) <= {-30.0, 30.0}
    assert 38 <= np.median(np.diff(lg.time)) <= 44  # about 24 Hz
    assert lg.meta.provenance["world"] == "diffdrive" and lg.meta.provenance["effects"]["noise"]["sigma"] == 2.0


def test_same_seed_same_logs_and_other_seed_other_logs():
    assert np.array_equal(_color(seed=3), _color(seed=3))
    assert not np.array_equal(_color(seed=3), _color(seed=4))


@pytest.mark.parametrize("name", sorted(set(EFFECTS) | set(NOVEL)))
def test_every_effect_changes_the_logs(name):
    value = {
        "saturation": {"low": 25.0, "high": 55.0},
        "steer_limit": 10.0,
        "jitter": {"pause_prob": 0.05},
        "quantise": 4.0,
    }
    effects = {name: value.get(name, True)}
    if name == "jitter":
        times = [lg.time for lg in generate_diffdrive(LANE, 4, 100, effects, seed=0)]
        assert max(np.diff(t).max() for t in times) > 1000
        return
    assert not np.array_equal(_color(effects), _color()), name


def test_unknown_effects_and_parameters_are_refused():
    with pytest.raises(ValueError, match="unknown diffdrive effect 'wind'"):
        resolve_diffdrive({"wind": 1.0})
    with pytest.raises(ValueError, match="unknown parameter"):
        resolve_diffdrive({"kick": {"size": 1.0}})
    assert resolve_diffdrive({"kick": 0, "delay": 2}) == {"delay": {"ticks": 2.0}}


def test_clean_logs_resemble_the_real_ones(real_logs):
    """Broadly, version by version: colour percentiles within 12 units and the oscillation period
    within a factor 1.5 of the real logs' (the comparison is printed; run with -s to see it)."""
    rows = resemblance(real_logs, runs=12)
    print("\n" + resemblance_table(rows))
    by = {(r["x"], r["source"]): r for r in rows}
    xs = sorted({r["x"] for r in rows})
    assert len(xs) == 5
    for x in xs:
        real, twin = by[(x, "real")], by[(x, "diffdrive")]
        assert np.max(np.abs(np.subtract(real["percentiles"], twin["percentiles"]))) <= 12, (x, real, twin)
        assert 1 / 1.5 <= twin["period"] / real["period"] <= 1.5, (x, real, twin)

"""Data-quality findings: every known defect injected into clean twin logs is found, with its file and
where; the clean twin logs give none; the pauses inside the real lane-keeping logs are flagged."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec
from envi_py.diagnose.data_quality import data_quality
from envi_py.twin import TwinProfile, generate

LANE = ControllerSpec("lane-keeping", {"x": 30})


@pytest.fixture(scope="module")
def clean():
    return generate(LANE, 24, 100, {}, seed=4, profile=TwinProfile())


def _check(logs):
    schema = logs[0].meta.schema
    return data_quality(logs, schema.states, schema.actions)


def _with(lg, **arrays):
    return replace(lg, **{k: np.array(v, dtype=np.float64) for k, v in arrays.items()})


def test_clean_twin_logs_have_no_finding(clean):
    assert _check(clean) == []


def test_a_pause_is_found_with_file_row_and_time(clean):
    lg = clean[3]
    time = lg.time.copy()
    time[41:] += 10_500.0  # a 10.5 s pause after row 40 of a 4 s log
    found = _check(clean[:3] + [_with(lg, time=time)] + clean[4:])
    assert [f.kind for f in found] == ["pause"]
    (where,) = found[0].where
    assert where["file"] == lg.name and where["row"] == 43  # data row 41, the header is row 1
    assert where["time_s"] == pytest.approx(1.6) and where["pause_s"] == pytest.approx(10.54)
    assert "10.5 s where the median interval is 40 ms" in found[0].what


def test_a_copied_log_and_a_block_sent_twice_are_found(clean):
    states = clean[5].states.copy()
    actions = clean[5].actions.copy()
    states[60:72], actions[60:72] = states[20:32], actions[20:32]
    copy = replace(clean[0], meta=replace(clean[0].meta, run_id="copy_of_0"))
    found = _check(clean[:5] + [_with(clean[5], states=states, actions=actions)] + clean[6:] + [copy])
    kinds = {(f.kind, f.files) for f in found}
    assert ("repeated", (clean[0].name, "copy_of_0")) in kinds
    block = next(f for f in found if f.files == (clean[5].name,))
    assert block.kind == "repeated" and block.where[0]["row"] == 62 and block.where[0]["repeats_row"] == 22


def test_a_frozen_sensor_is_found(clean):
    states = clean[7].states.copy()
    states[30:70, 0] = states[30, 0]
    found = _check(clean[:7] + [_with(clean[7], states=states)] + clean[8:])
    assert [f.kind for f in found] == ["frozen"]
    assert found[0].files == (clean[7].name,) and found[0].where[0] == {
        "file": clean[7].name,
        "row": 32,
        "rows": 40,
        "seconds": pytest.approx(1.56),
        "value": pytest.approx(states[30, 0]),
    }


def test_a_held_command_and_a_saturating_sensor_at_its_limit_are_not_frozen(clean):
    """A command held for a whole run is the controller's choice (the car's speed loop at its output
    limit), and a saturating sensor resting at its limit reads "nothing in range" (the car's 255 cm):
    neither is a logger that stopped. A saturating sensor frozen away from its limit still is."""
    actions = clean[7].actions.copy()
    actions[:, 0] = actions[0, 0]
    assert _check(clean[:7] + [_with(clean[7], actions=actions)] + clean[8:]) == []
    schema = clean[0].meta.schema
    sat = [replace(schema.states[0], saturates=True)]
    at_limit, away = clean[7].states.copy(), clean[7].states.copy()
    at_limit[30:70, 0] = sat[0].high
    away[30:70, 0] = away[30, 0]
    logs = clean[:7] + [_with(clean[7], states=at_limit)] + clean[8:]
    assert data_quality(logs, sat, schema.actions) == []
    logs = clean[:7] + [_with(clean[7], states=away)] + clean[8:]
    assert [f.kind for f in data_quality(logs, sat, schema.actions)] == ["frozen"]


def test_a_reading_outside_the_declared_range_is_found(clean):
    states = clean[2].states.copy()
    states[50, 0] = 130.0
    found = _check(clean[:2] + [_with(clean[2], states=states)] + clean[3:])
    assert [f.kind for f in found] == ["out_of_range"]
    assert found[0].where == [{"file": clean[2].name, "row": 52, "count": 1, "value": 130.0}]
    assert "range [0, 100] %" in found[0].what


def test_a_session_that_differs_as_a_block_is_found(clean):
    # the last 6 of 24 logs in file order (twin_4_18..twin_4_23): a session 8 % brighter
    shifted = [_with(lg, states=lg.states + 8.0) for lg in clean[18:]]
    found = _check(clean[:18] + shifted)
    assert [f.kind for f in found] == ["session"]
    assert set(found[0].files) == {lg.name for lg in shifted}
    assert "in the mean of color" in found[0].what


def test_pauses_in_the_real_logs_are_flagged(real_logs):
    logs = [lg for lg in real_logs if lg.param.get("x") == 10]
    schema = logs[0].meta.schema
    pauses = [f for f in data_quality(logs, schema.states, schema.actions) if f.kind == "pause"]
    assert len(pauses) == 1
    where = {w["file"]: w for w in pauses[0].where}
    # a 4 s log (100 rows of ~41 ms) holding a pause of more than 9 s
    assert {"log_10_1.csv", "log_10_5.csv", "log_10_13.csv"} <= set(where)
    assert all(w["pause_s"] > 9.0 for w in where.values())
    assert where["log_10_1.csv"]["row"] == 38

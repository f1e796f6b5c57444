"""System descriptions: the shipped ones parse, every mistake is one clear error naming the file."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.system import LogSchema, SystemDescription, Versions, load_system, pattern_regex, shipped


def test_shipped_descriptions_parse_and_round_trip_through_json():
    assert {"lane-keeping", "car"} <= set(shipped())
    for name in shipped():
        d = load_system(name)
        back = SystemDescription.from_json(d.to_json())
        assert back.schema == d.schema and back.controller == d.controller and back.goals == d.goals


def test_car_declares_two_states_two_actions_and_logged_pid_terms():
    d = load_system("car")
    assert [c.name for c in d.schema.states] == ["color", "distance"]
    assert [c.name for c in d.schema.actions] == ["steering", "speed"]
    assert len(d.schema.logged) == 6 and d.schema.states[1].saturates
    spec = d.controller_for({"kp_steer": 2.5})
    assert spec.params["loops"][0]["params"]["kp"] == 2.5
    assert spec.build(2, 2, 40.0)  # widths fit


def test_version_fields_from_a_pattern_become_controller_parameters():
    d = load_system("lane-keeping").with_pattern("log_{x}_{run}.csv")
    assert d.versions.params == ("x",)
    assert d.controller_for({"x": 30}) == ControllerSpec("lane-keeping", {"x": 30})


def test_a_contradicting_pattern_is_an_error_not_an_override():
    d = load_system("lane-keeping").with_pattern("log_{x}_{run}.csv")
    with pytest.raises(ValueError, match="contradicts"):
        d.with_pattern("run_{run}_{x}.csv")


@pytest.mark.parametrize(
    "pattern, why", [("log_{x}_{x}.csv", "appears twice"), ("log_{x.csv", "brace"), ("", "non-empty")]
)
def test_bad_patterns_are_value_errors(pattern, why):
    with pytest.raises(ValueError, match=why):
        pattern_regex(pattern)


@pytest.mark.parametrize(
    "text, why",
    [
        ("[system\n", "not valid TOML"),
        ("[system]\nname='x'\n", "no \\[\\[signals\\]\\]"),
        ("[[signals]]\nname='a'\nrole='state'\n", "at least one 'state' and one 'action'"),
        ("[[signals]]\nname='a'\nrole='sensor'\n", "role must be one of"),
        ("[[signals]]\nname='a'\nrole='state'\nrange=[5, 1]\n[[signals]]\nname='b'\nrole='action'\n", "is empty"),
        ("[[signals]]\nname='a'\nrole='state'\n[[signals]]\nname='a'\nrole='action'\n", "twice"),
        (
            "[[signals]]\nname='a'\nrole='state'\n[[signals]]\nname='b'\nrole='action'\n"
            "[[goals]]\nmetric='max'\nsignal='zz'\n",
            "not declared",
        ),
        (
            "[[signals]]\nname='a'\nrole='state'\n[[signals]]\nname='b'\nrole='action'\n"
            "[[requirements]]\nexpr='max(a) <= 1'\nprobability=1.5\n",
            "strictly between",
        ),
    ],
)
def test_malformed_descriptions_name_the_file(tmp_path: Path, text: str, why: str):
    f = tmp_path / "sys.toml"
    f.write_text(text)
    with pytest.raises(ValueError, match=why) as exc:
        SystemDescription.load(f)
    assert str(f) in str(exc.value)


def test_schema_from_json_rejects_wrong_types():
    for bad in ([], "x", {"states": [], "actions": [{"name": "a"}]}, {"states": [{"name": 3}], "actions": []}):
        with pytest.raises(ValueError):
            LogSchema.from_json(bad)


SIGNALS = "[[signals]]\nname='a'\nrole='state'\n[[signals]]\nname='b'\nrole='action'\n"


@pytest.mark.parametrize(
    "extra, why",
    [
        ("[versions]\nparams = 'xy'\n", "must be a list"),  # once read as the two names 'x' and 'y'
        ("[versions]\nmap = {x = 3}\n", "table of parameter paths"),
        ("[versions]\npattern = 5\n", "non-empty string"),
        ("[versions]\npattern = 'log_{0}.csv'\n", "not a name"),  # once a re.error traceback
        ("[system]\nname = [1]\n", "'name' must be a string"),
        ("[system]\ngoals_preset = false\n", "'goals_preset' must be a string"),
        ("goals = 5\n", "'goals' must be a list"),
    ],
)
def test_wrongly_typed_description_fields_are_refused(tmp_path: Path, extra: str, why: str):
    f = tmp_path / "sys.toml"
    f.write_text(extra + SIGNALS)
    with pytest.raises(ValueError, match=why) as exc:
        SystemDescription.load(f)
    assert str(f) in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize(
    "channel, why",
    [
        ({"name": "a", "range": [0, "100"]}, "two numbers"),  # once float("100") silently
        ({"name": "a", "range": [True, 5]}, "two numbers"),
        ({"name": "a", "unit": ["m"]}, "'unit' must be a string"),
        ({"name": "a", "saturates": "no"}, "true or false"),  # once bool("no") == True
        ({"name": "a,b"}, "cannot be a CSV column"),
        ({"name": " a"}, "cannot be a CSV column"),
    ],
)
def test_channel_fields_are_typed(channel, why):
    with pytest.raises(ValueError, match=why):
        LogSchema.from_json({"states": [channel], "actions": [{"name": "u"}]})


def test_recorded_descriptions_check_pattern_and_lists():
    d = load_system("lane-keeping").to_json()
    for key, value, why in [
        ("versions", {"pattern": "{"}, "brace"),
        ("ignore", "abc", "list"),
        ("versions", [], "'versions' must be an object"),
    ]:
        with pytest.raises(ValueError, match=why):
            SystemDescription.from_json({**d, key: value}, "ckpt")


def test_a_version_path_through_a_number_is_a_value_error():
    car = load_system("car")
    for path in ("loops.9.params.kp", "loops.0.name.kp", "loops.x"):
        d = replace(car, versions=Versions(None, ("k",), {"k": path}))
        with pytest.raises(ValueError, match="does not lead into"):  # once IndexError / AttributeError
            d.controller_for({"k": 1})


def test_with_pattern_refuses_a_non_string():
    with pytest.raises(ValueError, match="non-empty string"):
        load_system("lane-keeping").with_pattern(5)  # a manifest's "pattern": 5 was a TypeError

"""The log reader: real logs load, every kind of bad file is reported with its file and row."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from envi_py.logs import (DatasetSpec, LogError, LogMeta, load_logs, pattern_regex, read_log, sidecar_path,
                          write_log)

from .conftest import REAL_PATTERN, make_log

GOOD = "time,color,angle\n0,71,30\n41,60,30\n82,35,-30\n"


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_real_logs_load_with_pattern_fields(real_logs):
    xs = sorted({lg.param["x"] for lg in real_logs})
    assert xs == [10, 20, 30, 40, 50]
    assert all(len(lg) == 100 for lg in real_logs)
    first = real_logs[0]
    assert first.name == "log_10_0.csv" and first.meta.run_id == "0"
    # natural order: log_10_2 before log_10_10
    names = [lg.name for lg in real_logs if lg.param["x"] == 10]
    assert names.index("log_10_2.csv") < names.index("log_10_10.csv")


def test_where_filters_parameters(real_dir):
    logs = load_logs(real_dir, DatasetSpec(pattern=REAL_PATTERN), where={"x": [10, 50]})
    assert {lg.param["x"] for lg in logs} == {10, 50}
    assert len(logs) == 40 + 66


def test_pattern_regex_fields():
    m = pattern_regex("log_{x}_{run}.csv").match("log_30_12.csv")
    assert m and m.group("x") == "30" and m.group("run") == "12"
    assert pattern_regex("log_{x}_{run}.csv").match("other_30_12.csv") is None


@pytest.mark.parametrize("text, expect", [
    ("time,color\n0,1\n", "missing column(s) angle"),
    ("time,color,angle,speed\n0,1,2,3\n", "unexpected column(s) speed"),
    ("time,color,angle\n0,71,30\n41,abc,30\n", "row 3: column 'color' has non-numeric value 'abc'"),
    ("time,color,angle\n0,71,30\n41,nan,30\n", "row 3: column 'color' is 'nan'"),
    ("time,color,angle\n0,71,30\n41,70,inf\n", "row 3: column 'angle' is 'inf'"),
    ("time,color,angle\n0,71,30\n41,70,30\n41,69,30\n", "row 4: time 41 does not increase"),
    ("time,color,angle\n0,71,30\n41,70\n", "row 3: 2 cells"),
    ("", "empty file"),
])
def test_bad_logs_name_file_and_row(tmp_path, text, expect):
    p = write(tmp_path, "bad.csv", text)
    with pytest.raises(LogError) as err:
        read_log(p)
    assert str(p) in str(err.value)
    assert expect in str(err.value)


def test_too_short_for_history(tmp_path):
    p = write(tmp_path, "short.csv", GOOD)
    with pytest.raises(LogError, match="shorter than the 11"):
        read_log(p, min_length=11)


def test_bad_file_in_folder_stops_or_is_skipped(tmp_path):
    write(tmp_path, "a.csv", GOOD)
    write(tmp_path, "b.csv", "time,color,angle\n0,x,1\n")
    with pytest.raises(LogError, match="b.csv"):
        load_logs(tmp_path)
    with pytest.warns(UserWarning, match="b.csv"):
        logs = load_logs(tmp_path, skip_bad=True)
    assert [lg.name for lg in logs] == ["a.csv"]


def test_mixed_schemas_rejected(tmp_path):
    write(tmp_path, "a.csv", GOOD)
    log = make_log(np.array([71.0, 60, 35]))
    other = LogMeta.from_json({**log.meta.to_json(), "states": [{"name": "distance", "unit": "m"}]}, "x")
    log.meta = other
    write_log(log, tmp_path / "b.csv")
    with pytest.raises(LogError, match="mixed schemas"):
        load_logs(tmp_path)


def test_write_read_round_trip_with_sidecar(tmp_path):
    log = make_log(np.array([71.0, 60.5, 35, 20]), x=20)
    log.meta.source = "sim"
    path = write_log(log, tmp_path / "sim" / "run.csv")
    back = read_log(path)
    np.testing.assert_array_equal(back.states, log.states)
    np.testing.assert_array_equal(back.actions, log.actions)
    assert back.meta.source == "sim" and back.param == {"x": 20}
    assert back.sha256() == log.sha256()
    # no temporary files left behind
    assert sorted(p.name for p in (tmp_path / "sim").iterdir()) == ["run.csv", "run.meta.json"]


def test_bad_sidecar(tmp_path):
    p = write(tmp_path, "a.csv", GOOD)
    sidecar_path(p).write_text(json.dumps({"schema_version": 99}))
    with pytest.raises(LogError, match="schema_version 99"):
        read_log(p)
    sidecar_path(p).write_text("{not json")
    with pytest.raises(LogError, match="not valid JSON"):
        read_log(p)


def test_manifest(tmp_path):
    write(tmp_path, "log_10_0.csv", GOOD)
    write(tmp_path, "log_20_0.csv", GOOD.replace(",30", ",20").replace("-30", "-20"))
    man = tmp_path / "m.json"
    man.write_text(json.dumps({"pattern": REAL_PATTERN, "logs": ["log_20_0.csv"]}))
    logs = load_logs(man)
    assert len(logs) == 1 and logs[0].param == {"x": 20}

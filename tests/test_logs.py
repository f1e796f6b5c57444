"""The log reader: real logs load, every kind of bad file is reported with its file and row."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from envi_py.logs import LogError, LogMeta, SIDECAR_KEYS, load_logs, pattern_regex, read_log, sidecar_path, write_log
from envi_py.system import lane_keeping

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
    logs = load_logs(real_dir, lane_keeping().with_pattern(REAL_PATTERN), where={"x": [10, 50]})
    assert {lg.param["x"] for lg in logs} == {10, 50}
    assert len(logs) == 40 + 66


def test_pattern_regex_fields():
    m = pattern_regex("log_{x}_{run}.csv").match("log_30_12.csv")
    assert m and m.group("x") == "30" and m.group("run") == "12"
    assert pattern_regex("log_{x}_{run}.csv").match("other_30_12.csv") is None


@pytest.mark.parametrize(
    "text, expect",
    [
        ("time,color\n0,1\n", "missing column(s) angle"),
        ("time,color,angle,speed\n0,1,2,3\n", "unexpected column(s) speed"),
        ("time,color,angle\n0,71,30\n41,abc,30\n", "row 3: column 'color' has non-numeric value 'abc'"),
        ("time,color,angle\n0,71,30\n41,nan,30\n", "row 3: column 'color' is 'nan'"),
        ("time,color,angle\n0,71,30\n41,70,inf\n", "row 3: column 'angle' is 'inf'"),
        ("time,color,angle\n0,71,30\n41,70,30\n41,69,30\n", "row 4: time 41 does not increase"),
        ("time,color,angle\n0,71,30\n41,70\n", "row 3: 2 cells"),
        ("", "empty file"),
    ],
)
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


# ------------------------------------------------------------ the reader against hostile and unlucky input


@pytest.mark.parametrize(
    "text, expect",
    [
        ("time,color,color,angle\n0,1,1,2\n", "appear twice in the header"),
        ("time,color,angle\n0,71,30\n,,\n", "row 3: an empty row"),
        ("time,color,angle\n0,71,30\n41,\u0661\u0662,30\n", "row 3: column 'color' has non-numeric value"),
        (
            "time,color,angle\n0,71,30\n41,1e308,30\n",
            "row 3: column 'color' is 1e+308, outside its valid range [0, 100]",
        ),
        ("time,color,angle\n0,71,30\n41,70,-200\n", "column 'angle' is -200, outside its valid range [-90, 90]"),
        ("time,color,angle\n0,71,30\n41,70,1e999\n", "out of the float range"),
        ("time,color,angle\n0,71,30\n41,70,30\x00\n", "NUL bytes"),
    ],
)
def test_hostile_cells_name_file_row_and_column(tmp_path, text, expect):
    p = write(tmp_path, "bad.csv", text)
    with pytest.raises(LogError) as err:
        read_log(p)
    assert str(p) in str(err.value) and expect in str(err.value)


def test_bom_and_crlf_files_are_read(tmp_path):
    p = tmp_path / "excel.csv"
    p.write_bytes("\ufefftime,color,angle\r\n0,71,30\r\n41,60,30\r\n".encode("utf-8"))
    log = read_log(p)
    assert log.states[:, 0].tolist() == [71, 60] and log.time.tolist() == [0, 41]
    side = sidecar_path(p)
    side.write_bytes(("\ufeff" + json.dumps(make_log(np.array([71.0, 60])).meta.to_json())).encode("utf-8"))
    assert read_log(p).meta.run_id == "r"


def test_fifo_and_device_links_are_refused_not_read(tmp_path):
    import os

    os.mkfifo(tmp_path / "pipe.csv")
    with pytest.raises(LogError, match="not a regular file"):
        read_log(tmp_path / "pipe.csv")
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    with pytest.raises(LogError, match="not a regular file"):
        read_log(tmp_path / "zero.csv")
    write(tmp_path, "ok.csv", GOOD)
    os.mkfifo(tmp_path / "ok.meta.json")
    with pytest.raises(LogError, match="ok.meta.json: not a regular file"):
        read_log(tmp_path / "ok.csv")


@pytest.mark.parametrize(
    "sidecar, expect",
    [
        ([1, 2], "must be a JSON object"),
        ("text", "must be a JSON object"),
        ({"schema_version": 1, "states": "color", "actions": []}, "sidecar"),
        ({**make_log(np.array([1.0])).meta.to_json(), "period_ms": [40]}, "period_ms"),
        ({**make_log(np.array([1.0])).meta.to_json(), "run_id": "../../X"}, "not a plain name"),
        ({**make_log(np.array([1.0])).meta.to_json(), "run_id": "/abs/path"}, "not a plain name"),
        ({**make_log(np.array([1.0])).meta.to_json(), "controller": "pid"}, "controller spec must be an object"),
        ({**make_log(np.array([1.0])).meta.to_json(), "provenance": [1]}, "provenance must be an object"),
    ],
)
def test_sidecars_of_the_wrong_type_are_one_clear_error(tmp_path, sidecar, expect):
    p = write(tmp_path, "a.csv", GOOD)
    sidecar_path(p).write_text(json.dumps(sidecar))
    with pytest.raises(LogError) as err:
        read_log(p)
    assert str(sidecar_path(p)) in str(err.value) and expect in str(err.value)


def test_deeply_nested_sidecar_is_an_error_not_a_recursion(tmp_path):
    p = write(tmp_path, "a.csv", GOOD)
    sidecar_path(p).write_text("[" * 100000 + "]" * 100000)
    with pytest.raises(LogError, match="a.meta.json"):
        read_log(p)
    with pytest.warns(UserWarning, match="a.meta.json"):
        with pytest.raises(LogError, match=r"every log was bad and skipped \(1\); the first: .*a\.meta\.json"):
            load_logs(tmp_path, skip_bad=True)


def test_declared_logged_and_ignored_columns(tmp_path):
    from envi_py.system import SystemDescription

    sysfile = write(
        tmp_path,
        "sys.toml",
        """
[[signals]]
name = "color"
role = "state"
range = [0, 100]
[[signals]]
name = "angle"
role = "action"
[[signals]]
name = "p_term"
role = "logged"
[[signals]]
name = "note"
role = "ignore"
[controller]
name = "lane-keeping"
[versions]
pattern = "run_{x}_{run}.csv"
""",
    )
    system = SystemDescription.load(sysfile)
    d = tmp_path / "logs"
    d.mkdir()
    write(d, "run_30_0.csv", "time,note,angle,color,p_term\n0,a,30,71,1.5\n40,b,30,60,2.5\n")
    (log,) = load_logs(d, system)
    assert log.param == {"x": 30} and log.logged[:, 0].tolist() == [1.5, 2.5]
    assert log.signal("p_term").tolist() == [1.5, 2.5] and log.signal("color").tolist() == [71, 60]
    back = read_log(write_log(log, tmp_path / "out" / "copy.csv"))
    assert back.meta.schema.columns == ["time", "color", "angle", "p_term"]
    assert back.logged.tolist() == log.logged.tolist()
    write(d, "run_30_1.csv", "time,angle,color,extra\n0,30,71,1\n40,30,60,1\n")
    with pytest.raises(LogError, match="unexpected column\\(s\\) extra \\(declare them"):
        load_logs(d, system)


def test_a_sidecar_contradicting_the_file_name_is_an_error(tmp_path):
    log = make_log(np.array([71.0, 60, 35]), x=20)
    write_log(log, tmp_path / "log_30_0.csv")
    with pytest.raises(LogError, match="the file name says x=30, its sidecar says x=20"):
        load_logs(tmp_path, lane_keeping().with_pattern(REAL_PATTERN))


def test_saturating_sensor_is_clipped_not_refused(tmp_path):
    from dataclasses import replace

    from envi_py.system import Channel, LogSchema

    schema = LogSchema((Channel("distance", "cm", 0, 255, 1.0, saturates=True),), (Channel("speed", "", 0, 720),))
    meta = LogMeta(schema=schema, controller={"name": "pid", "params": {}}, run_id="r")
    p = write(tmp_path, "d.csv", "time,distance,speed\n0,300,100\n40,20,100\n")
    assert read_log(p, meta).states[:, 0].tolist() == [255, 20]
    with pytest.raises(LogError, match="outside its valid range"):
        read_log(p, replace(meta, schema=LogSchema((replace(schema.states[0], saturates=False),), schema.actions)))


def test_split_manifests_carry_the_system_and_read_back_alone(real_dir, tmp_path):
    from envi_py.cli import main

    assert (
        main(
            [
                "split",
                "--logs",
                str(real_dir),
                "--pattern",
                REAL_PATTERN,
                "--where",
                "x=10,30,50",
                "--train",
                "5",
                "--val",
                "2",
                "--test",
                "3",
                "--mode",
                "blocks",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    train, test = load_logs(tmp_path / "train.json"), load_logs(tmp_path / "test.json")
    assert sorted({lg.param["x"] for lg in train}) == [10, 30, 50] and len(train) == 15
    assert sorted({lg.param["x"] for lg in test}) == [10, 30, 50] and len(test) == 9
    # blocks: each version's test logs are its last files, training its first
    assert max(int(lg.meta.run_id) for lg in train if lg.param["x"] == 10) < min(
        int(lg.meta.run_id) for lg in test if lg.param["x"] == 10
    )


def test_row_numbers_count_blank_lines_for_every_kind_of_error(tmp_path):
    """Cell, time and range errors all name the file's own line (blank lines count)."""
    for body, row in [("0,71,30\n\n40,x,30\n", 4), ("0,71,30\n\n0,60,30\n", 4), ("0,71,30\n\n\n40,101,30\n", 5)]:
        p = write(tmp_path, "gap.csv", "time,color,angle\n" + body)
        with pytest.raises(LogError, match=f": row {row}: "):
            read_log(p)


@pytest.mark.parametrize(
    "field, value, why",
    [
        ("schema_version", True, "schema_version"),  # True == 1 once passed
        ("provenance", [], "provenance must be an object"),
        ("controller", {"name": "lane-keeping", "params": {"x": 1e999}}, "non-finite"),
    ],
)
def test_sidecar_fields_are_typed(tmp_path, field, value, why):
    p = write(tmp_path, "a.csv", GOOD)
    sidecar_path(p).write_text(json.dumps({**LogMeta().to_json(), field: value}))
    with pytest.raises(LogError, match=why):
        read_log(p)


def test_a_sidecar_key_the_reader_does_not_know_is_refused_naming_it(tmp_path):
    """A hand-written sidecar with ``period`` for ``period_ms`` once read as if it gave no period."""
    p = write(tmp_path, "a.csv", GOOD)
    sidecar_path(p).write_text(json.dumps({**LogMeta().to_json(), "period": 40}))
    with pytest.raises(LogError, match=r"a\.meta\.json: sidecar key\(s\) 'period' unknown; known: actions, breaks"):
        read_log(p)
    assert set(LogMeta(breaks=(3,)).to_json()) <= SIDECAR_KEYS  # what the writer writes, the reader knows


def test_sidecars_refuse_nan_and_deep_nesting(tmp_path):
    p = write(tmp_path, "a.csv", GOOD)
    meta = LogMeta().to_json()
    sidecar_path(p).write_text(json.dumps({**meta, "period_ms": float("nan")}))
    with pytest.raises(LogError, match="NaN"):
        read_log(p)
    sidecar_path(p).write_text(json.dumps(meta)[:-1] + ', "provenance": {"a": ' + "[" * 40 + "]" * 40 + "}}")
    with pytest.raises(LogError, match="nested deeper"):
        read_log(p)


def test_a_blank_header_name_is_named(tmp_path):
    p = write(tmp_path, "a.csv", "time,color,angle,\n0,1,2,\n")
    with pytest.raises(LogError, match="row 1: column 4 of the header has no name"):
        read_log(p)

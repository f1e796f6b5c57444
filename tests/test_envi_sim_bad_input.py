"""Bad input to envi_sim, the native binary: one stderr line naming the file or option, exit code 2,
nothing written to the output folder. The log format exists twice (envi_py/logs.py and
cpp/src/csvlog.cpp), so every corrupted initial log and sidecar here is given to both readers: the
Python reader must refuse it (a ValueError naming the file) and envi_sim must refuse it too, so the
two cannot drift apart. The option cases are envi_sim's own command line."""

from __future__ import annotations

import json
import os
import re
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from envi_py.export import export
from envi_py.logs import Log, load_logs, sidecar_path, write_log

from .conftest import make_log
from .test_export import paper_ckpt
from .test_native import envi_sim

pytestmark = pytest.mark.skipif(envi_sim() is None, reason="envi_sim binary not built")

HISTORY = 10  # paper_ckpt's window
ROWS = 20


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """The paper's lane-keeping model (history 10), exported once for the module."""
    return export(paper_ckpt(), tmp_path_factory.mktemp("model") / "m.onnx")


def good_lines() -> list[str]:
    """A valid bare lane-keeping log (time,color,angle; no sidecar) as CSV lines."""
    color = np.clip(40 + 25 * np.sin(np.arange(ROWS) / 3), 0, 100).round()
    angle = np.sign(color - 40) * 30
    return ["time,color,angle"] + [f"{40 * i},{c:g},{a:g}" for i, (c, a) in enumerate(zip(color, angle))]


def replace_cell(lines: list[str], row: int, col: int, value: str) -> list[str]:
    """The lines with one cell changed; `row` counts the header as row 1, as the messages do."""
    out = list(lines)
    cells = out[row - 1].split(",")
    cells[col] = value
    out[row - 1] = ",".join(cells)
    return out


def run_sim(model: Path, init: list[Path], tmp_path: Path, *options: str) -> subprocess.CompletedProcess:
    """envi_sim writing logs into tmp_path/sim and metrics into tmp_path/m.json (unless the options
    say otherwise), with a timeout: a hang is a failure, not a stuck test run."""
    cmd = [envi_sim(), "--model", str(model), "--init", *map(str, init), "--steps", "5", *options]
    if "--out" not in options:
        cmd += ["--out", str(tmp_path / "sim")]
    if "--metrics" not in options and "--metrics-only" not in options:
        cmd += ["--metrics", str(tmp_path / "m.json")]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)


def assert_refused(done: subprocess.CompletedProcess, tmp_path: Path, named: str) -> str:
    """Exit 2, one stderr line starting 'envi_sim: ' that holds `named`, nothing written."""
    lines = done.stderr.splitlines()
    assert done.returncode == 2, (done.returncode, done.stderr)
    assert len(lines) == 1 and lines[0].startswith("envi_sim: ") and named in lines[0], done.stderr
    assert done.stdout == ""
    assert not (tmp_path / "sim").exists() and not (tmp_path / "m.json").exists()
    return lines[0]


def assert_same_row(python: str, native: str) -> None:
    """Where both messages name a row, it is the same row."""
    rows = [re.search(r"\brow (\d+)\b", m) for m in (python, native)]
    if all(rows):
        assert rows[0].group(1) == rows[1].group(1), (python, native)


# ---------------------------------------------------------------- corrupted CSV logs (no sidecar)

LINES = good_lines()
CSV_CASES: dict[str, Callable[[], bytes]] = {
    "time decreases": lambda: "\n".join(replace_cell(LINES, 7, 0, "1")).encode(),
    "time repeats": lambda: "\n".join(replace_cell(LINES, 7, 0, "160")).encode(),
    "last row truncated": lambda: ("\n".join(LINES[:-1] + [LINES[-1].rsplit(",", 1)[0]]) + "\n").encode(),
    "last row cut after a separator": lambda: ("\n".join(LINES[:-1] + [LINES[-1].rsplit(",", 1)[0] + ","])).encode(),
    "state above its range": lambda: "\n".join(replace_cell(LINES, 8, 1, "150")).encode(),
    "action below its range": lambda: "\n".join(replace_cell(LINES, 15, 2, "-200")).encode(),
    "range error after the history": lambda: "\n".join(replace_cell(LINES, ROWS, 1, "101")).encode(),
    "NaN cell": lambda: "\n".join(replace_cell(LINES, 4, 1, "nan")).encode(),
    "inf cell": lambda: "\n".join(replace_cell(LINES, 4, 2, "-inf")).encode(),
    "beyond the float range": lambda: "\n".join(replace_cell(LINES, 4, 0, "1e999")).encode(),
    "non-numeric cell": lambda: "\n".join(replace_cell(LINES, 5, 1, "dark")).encode(),
    "hex cell": lambda: "\n".join(replace_cell(LINES, 5, 1, "0x10")).encode(),
    "extra cell": lambda: "\n".join(LINES[:3] + [LINES[3] + ",7"] + LINES[4:]).encode(),
    "row of separators": lambda: "\n".join(LINES[:3] + [",,"] + LINES[3:]).encode(),
    "blank line of spaces": lambda: "\n".join(LINES[:3] + ["   "] + LINES[3:]).encode(),
    "missing column": lambda: "\n".join(line.rsplit(",", 1)[0] for line in LINES).encode(),
    "column twice": lambda: "\n".join(["time,color,color"] + LINES[1:]).encode(),
    "header name blank": lambda: "\n".join(["time,,angle"] + LINES[1:]).encode(),
    "shorter than the history": lambda: "\n".join(LINES[: HISTORY - 2]).encode(),
    "header only": lambda: (LINES[0] + "\n").encode(),
    "column the system does not declare": lambda: "\n".join(
        [LINES[0] + ",foo"] + [line + ",1" for line in LINES[1:]]
    ).encode(),
    "empty file": lambda: b"",
    "NUL bytes": lambda: "\n".join(LINES).encode().replace(b"\n4", b"\n\x004", 1),
    "not UTF-8": lambda: "\n".join(LINES).encode().replace(b"color", b"col\xf6r", 1),
}


@pytest.mark.parametrize("case", list(CSV_CASES))
def test_a_corrupted_log_is_refused_by_both_readers(case, model, tmp_path):
    path = tmp_path / "log_30_0.csv"
    path.write_bytes(CSV_CASES[case]())
    with pytest.raises(ValueError) as err:
        load_logs([path], min_length=HISTORY)
    python = str(err.value)
    assert str(path) in python and "\n" not in python
    native = assert_refused(run_sim(model, [path], tmp_path), tmp_path, str(path))
    assert_same_row(python, native)
    if case == "header only":  # the problem itself, not a window length or a break that is not there
        assert "no data rows (only a header)" in python and "no data rows (only a header)" in native


def test_the_uncorrupted_log_passes_both_readers(model, tmp_path):
    """The cases above start from a log both readers accept: each refusal is the corruption's."""
    path = tmp_path / "log_30_0.csv"
    path.write_text("\n".join(LINES) + "\n")
    assert len(load_logs([path], min_length=HISTORY)[0]) == ROWS
    done = run_sim(model, [path], tmp_path)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (tmp_path / "sim").iterdir()) == ["log_30_0-sim0.csv", "log_30_0-sim0.meta.json"]


def test_an_out_folder_with_a_trailing_slash_is_created(model, init_log, tmp_path):
    """The checks of --out before any work read 'sim/' as the folder sim, as the usage shows it."""
    done = run_sim(model, [init_log], tmp_path, "--out", f"{tmp_path / 'sim'}/")
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "sim" / "log_30_0-sim0.csv").is_file()


#: Bytes a damaged or hand-edited CSV tends to hold: digits, separators, signs, line ends, quotes,
#: the letters of nan/inf/hex, a NUL and a byte that is not UTF-8.
DAMAGE = b'0123456789,.-+eE\n\r "naifx\x00\xff'


@settings(max_examples=60, deadline=None, database=None)
@given(
    edits=st.lists(
        st.tuples(st.sampled_from(["set", "delete", "insert"]), st.integers(0, 10_000), st.sampled_from(DAMAGE)),
        min_size=1,
        max_size=3,
    )
)
def test_both_readers_agree_on_a_damaged_log(model, edits):
    """A valid log with a few bytes changed, deleted or inserted: envi_sim accepts it exactly when
    the Python reader does, and never crashes (exit 0 or 2, one line when refused)."""
    data = bytearray(("\n".join(LINES) + "\n").encode())
    for op, where, byte in edits:
        i = where % len(data)
        if op == "set":
            data[i] = byte
        elif op == "delete":
            del data[i]
        else:
            data.insert(i, byte)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "log_30_0.csv"
        path.write_bytes(bytes(data))
        try:
            load_logs([path], min_length=HISTORY)
            python_accepts = True
        except ValueError:
            python_accepts = False
        done = run_sim(model, [path], Path(d), "--metrics-only", "--metrics", "-")
    assert done.returncode in (0, 2), done.stderr
    assert (done.returncode == 0) == python_accepts, (bytes(data), done.stderr)
    if done.returncode == 2:
        assert len(done.stderr.splitlines()) == 1 and str(path) in done.stderr


def test_a_fifo_is_refused_without_hanging(model, tmp_path):
    path = tmp_path / "log_30_0.csv"
    os.mkfifo(path)
    with pytest.raises(ValueError, match="not a regular file") as err:
        load_logs([path], min_length=HISTORY)
    assert str(path) in str(err.value)
    line = assert_refused(run_sim(model, [path], tmp_path), tmp_path, str(path))
    assert "not a regular file" in line


# ---------------------------------------------------------------- corrupted sidecars


def sidecar_json() -> tuple[Log, dict]:
    """The sidecar write_log writes for a valid lane-keeping log."""
    log = make_log(np.clip(40 + 25 * np.sin(np.arange(ROWS) / 3), 0, 100).round(), run="log_30_0")
    return log, json.loads(json.dumps(log.meta.to_json()))


def nest(depth: int) -> list:
    node: list = []
    for _ in range(depth - 1):
        node = [node]
    return node


SIDECAR_CASES: dict[str, Callable[[dict], str | dict]] = {
    "bad JSON": lambda d: "{bad",
    "truncated JSON": lambda d: json.dumps(d)[:-7],
    "NaN": lambda d: json.dumps({**d, "period_ms": float("nan")}),
    "number with a leading zero": lambda d: json.dumps(d).replace('"schema_version": 1', '"schema_version": 01'),
    "number ending in a point": lambda d: json.dumps(d).replace('"period_ms": 40.0', '"period_ms": 40.'),
    "line break inside a string": lambda d: json.dumps(d).replace('"unit": "%"', '"unit": "%\n"'),
    "not an object": lambda d: "[1, 2]",
    "schema_version 2": lambda d: {**d, "schema_version": 2},
    "schema_version 1.0": lambda d: {**d, "schema_version": 1.0},
    "unknown source": lambda d: {**d, "source": "lab"},
    "misspelt key": lambda d: {**d, "period": 40},
    "run id with a path": lambda d: {**d, "run_id": "../../etc/x"},
    "run id an object": lambda d: {**d, "run_id": {"a": 1}},
    "period_ms negative": lambda d: {**d, "period_ms": -40},
    "period_ms a string": lambda d: {**d, "period_ms": "40"},
    "empty range": lambda d: {**d, "states": [{**d["states"][0], "range": [50, 10]}]},
    "range of strings": lambda d: {**d, "states": [{**d["states"][0], "range": ["0", "100"]}]},
    "saturates not a bool": lambda d: {**d, "states": [{**d["states"][0], "saturates": "no"}]},
    "no states": lambda d: {**d, "states": []},
    "column named twice": lambda d: {**d, "actions": [{**d["actions"][0], "name": "color"}]},
    "controller params a list": lambda d: {**d, "controller": {"name": "lane-keeping", "params": [1]}},
    "controller gain a string": lambda d: {**d, "controller": {"name": "lane-keeping", "params": {"x": "ten"}}},
    "controller reading a state the log lacks": lambda d: {**d, "controller": {"name": "pid", "params": {"input": 3}}},
    "controller params infinite": lambda d: json.dumps(
        {**d, "controller": {"name": "lane-keeping", "params": {"x": float("inf")}}}
    ),
    "provenance a list": lambda d: {**d, "provenance": [1]},
    "nested too deep": lambda d: {**d, "provenance": {"deep": nest(40)}},
    "another system's states": lambda d: {**d, "states": [{**d["states"][0], "name": "speed"}]},
    "value outside the sidecar's range": lambda d: {**d, "states": [{**d["states"][0], "range": [0, 50]}]},
    "breaks not a list": lambda d: {**d, "breaks": 0},
    "breaks of strings": lambda d: {**d, "breaks": ["5"]},
    "breaks of fractions": lambda d: {**d, "breaks": [5.0]},
    "breaks of booleans": lambda d: {**d, "breaks": [True]},
    "breaks at row 0": lambda d: {**d, "breaks": [0]},
    "breaks not increasing": lambda d: {**d, "breaks": [9, 9]},
    "break beyond the log": lambda d: {**d, "breaks": [ROWS]},
}


def test_a_manifest_given_as_a_log_says_so(model, tmp_path):
    """envi_sim reads logs, not manifests: a split's test.json given to --init said 'row 1: missing
    column(s) time, color, angle'."""
    path = tmp_path / "test.json"
    path.write_text(json.dumps({"pattern": "log_{x}_{run}.csv", "logs": ["log_30_0.csv"]}))
    line = assert_refused(run_sim(model, [path], tmp_path), tmp_path, str(path))
    assert "a JSON file (a manifest?), not a CSV log" in line


@pytest.mark.parametrize("case", list(SIDECAR_CASES))
def test_a_corrupted_sidecar_is_refused_by_both_readers(case, model, tmp_path):
    log, meta = sidecar_json()
    path = write_log(log, tmp_path / "log_30_0.csv")
    side = sidecar_path(path)
    content = SIDECAR_CASES[case](meta)
    side.write_text(content if isinstance(content, str) else json.dumps(content, indent=1))
    with pytest.raises(ValueError) as err:
        load_logs([path], min_length=HISTORY)
    python = str(err.value)
    # the sidecar is named when it is itself bad, the log when the two disagree
    own = ("another system's states", "value outside the sidecar's range", "break beyond the log")
    named = str(path) if case in own else str(side)
    assert named in python and "\n" not in python, python
    native = assert_refused(run_sim(model, [path], tmp_path), tmp_path, named)
    assert_same_row(python, native)


def test_a_sidecar_folder_is_refused_by_both_readers(model, tmp_path):
    log, _ = sidecar_json()
    path = write_log(log, tmp_path / "log_30_0.csv")
    side = sidecar_path(path)
    side.unlink()
    side.mkdir()
    with pytest.raises(ValueError, match="not a regular file"):
        load_logs([path], min_length=HISTORY)
    assert "not a regular file" in assert_refused(run_sim(model, [path], tmp_path), tmp_path, str(side))


def test_a_saturating_sensor_is_clipped_by_both_readers(model, tmp_path):
    """A value beyond a saturating channel's range is its limit, not an error, on both sides: the
    simulated log's initial window holds the clipped readings the Python reader returns."""
    log, meta = sidecar_json()
    path = write_log(log, tmp_path / "log_30_0.csv")
    meta["states"] = [{**meta["states"][0], "range": [0, 50], "saturates": True}]
    sidecar_path(path).write_text(json.dumps(meta, indent=1))
    python = load_logs([path], min_length=HISTORY)[0]
    assert python.states[:, 0].max() == 50 and log.states[:HISTORY, 0].max() > 50
    done = run_sim(model, [path], tmp_path)
    assert done.returncode == 0, done.stderr
    sim = load_logs([tmp_path / "sim" / "log_30_0-sim0.csv"])[0]
    np.testing.assert_array_equal(sim.values[:HISTORY], python.values[:HISTORY])


# ---------------------------------------------------------------- options


def fifo(tmp_path: Path) -> Path:
    path = tmp_path / "fifo"
    os.mkfifo(path)
    return path


def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("x")
    return path


#: Options envi_sim must refuse: the extra arguments and the text its error line must hold, both
#: from the test's folder.
OPTION_CASES: dict[str, Callable[[Path], tuple[list[str], str]]] = {
    "runs beyond memory and disk": lambda t: (["--runs", "99999999999"], "--runs 99999999999"),
    "runs beyond memory to stdout": lambda t: (["--runs", "99999999999", "--metrics-only", "--metrics", "-"], "--runs"),
    "runs overflowing 64 bits": lambda t: (["--runs", "99999999999999999999"], "--runs"),
    "runs zero": lambda t: (["--runs", "0"], "--runs"),
    "runs fractional": lambda t: (["--runs", "1.5"], "--runs"),
    "steps negative": lambda t: (["--steps", "-1"], "--steps"),
    "steps beyond the step counter": lambda t: (["--steps", "99999999999"], "--steps"),
    "skip negative": lambda t: (["--skip", "-1"], "--skip"),
    "skip past the run": lambda t: (["--skip", "1000"], "--skip"),
    "threads negative": lambda t: (["--threads", "-1"], "--threads"),
    "threads beyond the limit": lambda t: (["--threads", "100000"], "--threads"),
    "threads not a number": lambda t: (["--threads", "2x"], "--threads"),
    "block zero": lambda t: (["--block", "0"], "--block"),
    "seed negative": lambda t: (["--seed", "-1"], "--seed"),
    "seed fractional": lambda t: (["--seed", "1e3"], "--seed"),
    "centre nan": lambda t: (["--centre", "nan"], "--centre"),
    "centre inf": lambda t: (["--centre=inf"], "--centre"),
    "band nan": lambda t: (["--band", "nan"], "--band"),
    "band negative": lambda t: (["--band", "-1"], "--band"),
    "param nan": lambda t: (["--controller", "lane-keeping", "--param", "x=nan"], "--param x=nan"),
    "param infinite": lambda t: (["--controller", "lane-keeping", "--param", "x=-Infinity"], "--param x=-Infinity"),
    "controller spec NaN": lambda t: (['--controller={"name": "lane-keeping", "params": {"x": NaN}}'], "--controller"),
    "controller spec bad JSON": lambda t: (['--controller={"name": '], "--controller"),
    "controller file a FIFO": lambda t: ([f"--controller=@{fifo(t)}"], str(t / "fifo")),
    "controller file missing": lambda t: ([f"--controller=@{t / 'none.json'}"], str(t / "none.json")),
    "out a file": lambda t: (["--out", str(a_file(t))], "--out"),
    "out in a missing folder": lambda t: (["--out", str(t / "none" / "sim")], "--out"),
    "out without a value": lambda t: (["--out", "--metrics", str(t / "m.json")], "--out"),
    "metrics in a missing folder": lambda t: (["--metrics", str(t / "none" / "m.json")], "--metrics"),
    "unknown option": lambda t: (["--bogus", "1"], "--bogus"),
}


@pytest.fixture()
def init_log(tmp_path) -> Path:
    path = tmp_path / "log_30_0.csv"
    path.write_text("\n".join(LINES) + "\n")
    return path


@pytest.mark.parametrize("case", list(OPTION_CASES))
def test_a_bad_option_is_refused_in_one_line(case, model, init_log, tmp_path):
    options, named = OPTION_CASES[case](tmp_path)
    assert_refused(run_sim(model, [init_log], tmp_path, *options), tmp_path, named)


@pytest.mark.parametrize("kind", ["missing", "folder", "fifo", "not onnx"])
def test_a_bad_model_file_is_refused_in_one_line(kind, init_log, tmp_path):
    bad = tmp_path / "bad.onnx"
    if kind == "folder":
        bad.mkdir()
    elif kind == "fifo":
        os.mkfifo(bad)
    elif kind == "not onnx":
        bad.write_bytes(b"\x08\x07garbage" * 10)
    assert_refused(run_sim(bad, [init_log], tmp_path), tmp_path, str(bad))


def test_two_initial_logs_with_one_run_id_are_refused_with_out(model, tmp_path):
    """Their simulated logs would overwrite each other in --out."""
    first, second = tmp_path / "a" / "log_30_0.csv", tmp_path / "b" / "log_30_0.csv"
    for p in (first, second):
        p.parent.mkdir()
        p.write_text("\n".join(LINES) + "\n")
    assert_refused(run_sim(model, [first, second], tmp_path), tmp_path, str(second))
    done = run_sim(model, [first, second], tmp_path, "--metrics-only", "--metrics", "-")
    assert done.returncode == 0, done.stderr  # without --out nothing collides


def test_metrics_json_is_strict(model, init_log, tmp_path):
    """The metrics document parses with NaN and Infinity refused: JSON has neither."""
    done = run_sim(model, [init_log], tmp_path, "--runs", "3", "--metrics-only", "--metrics", "-")
    assert done.returncode == 0, done.stderr

    def refuse(name: str) -> float:
        raise ValueError(f"non-finite {name} in the metrics JSON")

    out = json.loads(done.stdout, parse_constant=refuse)
    assert len(out["per_run"]) == 3 and out["config"]["centre"] == 40.0


def test_both_readers_take_the_columns_the_system_description_declares(tmp_path):
    """Without a sidecar a log holds what the model's recorded system description declares: its
    states and actions, its logged columns (required), and may hold its ignored ones; any other
    column is refused by both readers, as a missing logged one is."""
    from dataclasses import replace

    from envi_py.system import Channel, lane_keeping

    base = lane_keeping()
    system = replace(base, schema=replace(base.schema, logged=(Channel("steer_p", "deg"),)), ignore=("note",))
    model = export(replace(paper_ckpt(), system=system), tmp_path / "sys.onnx")
    rows = [f"{line},{k % 7},x" for k, line in enumerate(LINES[1:])]

    def both(header: str, body: list[str], name: str) -> tuple[str | None, subprocess.CompletedProcess]:
        folder = tmp_path / name
        folder.mkdir()
        path = folder / "log_30_0.csv"
        path.write_text("\n".join([header, *body]) + "\n")
        try:
            load_logs([path], system, min_length=HISTORY)
            python = None
        except ValueError as err:
            python = str(err)
        return python, run_sim(model, [path], folder)

    python, done = both(LINES[0] + ",steer_p,note", rows, "declared")
    assert python is None and done.returncode == 0, (python, done.stderr)
    python, done = both(LINES[0] + ",steer_p,foo", rows, "undeclared")
    assert python is not None and "unexpected column(s) foo" in python
    assert "unexpected column(s) foo" in assert_refused(done, tmp_path / "undeclared", "log_30_0.csv")
    python, done = both(LINES[0] + ",note", [r.rsplit(",", 2)[0] + ",x" for r in rows], "no-logged")
    assert python is not None and "missing column(s) steer_p" in python
    assert "missing column(s) steer_p" in assert_refused(done, tmp_path / "no-logged", "log_30_0.csv")


@pytest.mark.parametrize("which", ["the initial log", "the model"])
def test_metrics_never_replace_an_input(which, model, init_log, tmp_path):
    """'--metrics log_30_0.csv' or '--metrics m.onnx' once replaced that input with JSON, exit 0."""
    target = init_log if which == "the initial log" else tmp_path / "copy.onnx"
    if which == "the model":
        target.write_bytes(model.read_bytes())
    before = target.read_bytes()
    done = run_sim(target if which == "the model" else model, [init_log], tmp_path, "--metrics", str(target))
    line = assert_refused(done, tmp_path, f"--metrics {target}: is an input of this command")
    assert line.endswith("; nothing overwritten")
    assert target.read_bytes() == before


def test_a_log_of_the_window_alone_is_refused_without_steps(model, tmp_path):
    """A log of exactly l rows once gave a 'simulated' log of sigma_0 alone, exit 0."""
    path = tmp_path / "log_30_0.csv"
    path.write_text("\n".join(LINES[: HISTORY + 1]) + "\n")
    cmd = [envi_sim(), "--model", str(model), "--init", str(path), "--out", str(tmp_path / "sim")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
    assert_refused(done, tmp_path, f"--init {path}: 10 rows, the model's window alone: no row is left to simulate")


def test_an_initial_log_of_another_period_is_refused(model, tmp_path):
    """The model was trained at 40 ms; rows 80 ms apart are another loop."""
    path = tmp_path / "log_30_0.csv"
    slow = [LINES[0]] + [f"{80 * i},{line.split(',', 1)[1]}" for i, line in enumerate(LINES[1:])]
    path.write_text("\n".join(slow) + "\n")
    done = run_sim(model, [path], tmp_path)
    assert_refused(
        done, tmp_path, f"--init {path}: its rows are 80 ms apart (median), the model was trained at a 40 ms"
    )

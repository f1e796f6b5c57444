"""Property-based fuzzing of every input envi reads (issue 16): CSV logs, sidecars, manifests,
file-name patterns, system descriptions and command lines.

The property is the same everywhere: a call either succeeds with a result that keeps the declared
contract (every value finite and inside its channel's range, time strictly increasing, the columns
the description declares) or fails with a ``LogError``/``ValueError`` of one line naming the file
(and the row where there is one); through ``envi_py.cli.main`` the exit code is 2 and stderr is one
line ``envi <cmd>: error: ...``. Anything else escaping (TypeError, RecursionError, re.error, ...)
fails the test, and so does a hang: risky inputs run under ``signal.alarm``.

Hypothesis generates the inputs (shrinking a failure to a minimal file is worth more than a
hand-written generator); the profile is derandomised, so every run tries the same inputs.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import signal
import tempfile
import warnings
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from envi_py.cli import main
from envi_py.logs import Log, LogError, LogMeta, load_logs, load_manifest, read_log, sidecar_path
from envi_py.system import (
    COLUMN_NAME,
    SystemDescription,
    lane_keeping,
    pattern_regex,
    shipped,
    toml_value,
)

settings.register_profile(
    "envi-fuzz",
    derandomize=True,
    deadline=None,
    database=None,
    print_blob=True,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.filter_too_much,
        HealthCheck.data_too_large,
        HealthCheck.large_base_example,
    ],
)
FUZZ = settings.get_profile("envi-fuzz")
#: Inputs generated per test, checked against MIN_TOTAL by the last test of the module.
GENERATED: Counter[str] = Counter()
MIN_TOTAL = 400
TIMEOUT_S = 10  # one input: far beyond the slowest legitimate read, short enough to fail fast

LANE = lane_keeping()
GOOD_CSV = "time,color,angle\n0,71,30\n40,60,30\n80,35,-30\n"


# ----------------------------------------------------------------------------- helpers


class Hang(Exception):
    """Raised by the alarm when one input takes longer than TIMEOUT_S."""


@contextlib.contextmanager
def deadline(seconds: int = TIMEOUT_S) -> Iterator[None]:
    """Fail (do not block the suite) when the body hangs: a FIFO, /dev/zero or a runaway loop."""

    def ring(signum: int, frame: Any) -> None:
        raise Hang(f"no answer within {seconds} s")

    old = signal.signal(signal.SIGALRM, ring)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def count(name: str) -> None:
    GENERATED[name] += 1


def assert_clean_error(exc: BaseException, *names: object) -> None:
    """One non-empty line that names one of ``names`` (a file, a pattern)."""
    msg = str(exc)
    assert msg.strip() and "\n" not in msg and "\r" not in msg, f"not one line: {msg!r}"
    assert any(str(n) in msg for n in names), f"{msg!r} names none of {names}"


def assert_contract(log: Log, columns: list[str] | None = None) -> None:
    """What an accepted log promises every consumer."""
    schema = log.meta.schema
    if columns is not None:
        assert schema.columns == columns
    n = len(log)
    assert n >= 1
    assert log.states.shape == (n, len(schema.states)) and log.actions.shape == (n, len(schema.actions))
    assert log.logged is not None and log.logged.shape == (n, len(schema.logged))
    assert np.isfinite(log.time).all() and np.all(np.diff(log.time) > 0)
    for arr, chans in ((log.states, schema.states), (log.actions, schema.actions), (log.logged, schema.logged)):
        assert np.isfinite(arr).all()
        for i, ch in enumerate(chans):
            assert (arr[:, i] >= ch.low).all() and (arr[:, i] <= ch.high).all(), (ch, arr[:, i])


def read_or_error(path: Path, *names: object, **kwargs: Any) -> Log | None:
    """read_log under the alarm: the log (contract checked) or None after a clean LogError."""
    try:
        with deadline():
            log = read_log(path, **kwargs)
    except LogError as exc:
        assert_clean_error(exc, path, *names)
        return None
    assert_contract(log)
    return log


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``envi <argv>`` in process: the exit code and stderr (argparse's own exits included)."""
    err = io.StringIO()
    with deadline(60), contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
    return code, err.getvalue()


def assert_cli_error(code: int, err: str, cmd: str) -> None:
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip() and "%|" not in ln]
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith(f"envi {cmd}: error: "), err


# ----------------------------------------------------------------------------- CSV logs

NUMBER_FORMATS = st.sampled_from(["{:d}", "{:.1f}", "{:+d}", "{:e}", " {:d} ", '"{:d}"'])  # all exact
#: Cells that are never a valid reading, whatever column they are in.
BAD_TOKENS = [
    "",
    " ",
    "abc",
    "nan",
    "NaN",
    "-nan",
    "inf",
    "-Infinity",
    "1e400",
    "-1e999",
    "1_0",
    "0x10",
    "--1",
    "1..2",
    "1e",
    "e5",
    "\u0661\u0662",
    "\uff11\uff12",
    "\u00bd",
    "1 2",
    "\u00a0",
    "None",
    "true",
]
NOT_A_NUMBER = st.one_of(
    st.sampled_from(BAD_TOKENS),
    st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters=',"\r\n\x00'), max_size=8).filter(
        lambda t: re.fullmatch(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?", t.strip()) is None
    ),
)
DEFECTS = (
    "not_a_number",
    "out_of_range",
    "time_not_increasing",
    "ragged_short",
    "ragged_long",
    "separator_row",
    "header_missing",
    "header_extra",
    "header_duplicate",
    "header_blank",
    "nul",
    "not_utf8",
    "no_rows",
)


@st.composite
def csv_cases(draw: st.DrawFn) -> tuple[bytes, np.ndarray | None, str | None, int | None]:
    """A lane-keeping CSV, well-formed up to at most one defect, in any harmless dress (BOM, CRLF
    or CR line ends, quoted and padded cells, reordered columns, blank lines): its bytes, the
    values it holds (time, color, angle) when it is valid, the defect, and the row it is on."""
    n = draw(st.integers(1, 6))
    times = sorted(draw(st.sets(st.integers(0, 10**6), min_size=n, max_size=n)))
    color = draw(st.lists(st.integers(0, 100), min_size=n, max_size=n))
    angle = draw(st.lists(st.integers(-90, 90), min_size=n, max_size=n))
    fmt = draw(NUMBER_FORMATS)
    rows = [[fmt.format(v) if "d" in fmt else fmt.format(float(v)) for v in r] for r in zip(times, color, angle)]
    header = ["time", "color", "angle"]
    defect = draw(st.sampled_from((None,) * 4 + DEFECTS))
    target = draw(st.integers(0, n - 1))
    col = draw(st.integers(0, 2))
    if defect == "not_a_number":
        rows[target][col] = draw(NOT_A_NUMBER)
    elif defect == "out_of_range":
        col = draw(st.integers(1, 2))
        limit = 100.0 if col == 1 else 90.0
        size = draw(st.one_of(st.floats(limit + 0.5, 1e308), st.just(1e308)))
        low = 0.0 if col == 1 else -90.0
        rows[target][col] = repr(draw(st.sampled_from([size, low - (size - limit)])))
    elif defect == "time_not_increasing" and n > 1:
        target = max(target, 1)
        rows[target][0] = str(times[target - 1] - draw(st.integers(0, 10)))
    elif defect == "ragged_short":
        del rows[target][col]
    elif defect == "ragged_long":
        rows[target].append("1")
    elif defect == "header_missing":
        del header[col]
    elif defect == "header_extra":
        header.append(draw(st.sampled_from(["speed", "Color", "x y", "colour"])))
        for r in rows:
            r.append("0")
    elif defect == "header_duplicate":
        header[col] = header[(col + 1) % 3]
    elif defect == "header_blank":
        header.append(draw(st.sampled_from(["", " "])))
        for r in rows:
            r.append("0")
    elif defect == "time_not_increasing":
        defect = None  # one row cannot go back in time
    perm = draw(st.permutations(range(len(header)))) if defect not in ("ragged_short", "ragged_long") else None
    if perm is not None:
        header = [header[i] for i in perm]
        rows = [[r[i] for i in perm] if len(r) == len(perm) else r for r in rows]
    if draw(st.booleans()):
        header = [f'"{h}"' if h.strip() else h for h in header]
    lines = [",".join(header)]
    row_line = {}
    for i, r in enumerate(rows):
        while draw(st.integers(0, 4)) == 0:
            lines.append("")  # a blank line: not a reading, but it is a line of the file
        if defect == "separator_row" and i == target:
            lines.append("," * draw(st.integers(1, 3)))
            row_line[i] = len(lines)
        lines.append(",".join(r))
        row_line.setdefault(i, len(lines))
    if defect == "no_rows":
        lines = lines[:1] if draw(st.booleans()) else []
    eol = draw(st.sampled_from(["\n", "\r\n", "\r"]))
    text = eol.join(lines) + (eol if draw(st.booleans()) else "")
    data = text.encode()
    if defect == "nul":
        k = draw(st.integers(0, len(data)))
        data = data[:k] + b"\x00" + data[k:]
    elif defect == "not_utf8":
        k = draw(st.integers(0, len(data)))
        data = data[:k] + draw(st.sampled_from([b"\xff", b"\xc3(", b"\x80", b"\xed\xa0\x80"])) + data[k:]
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data
    expected = np.array([times, color, angle], dtype=float).T if defect is None else None
    row = (
        row_line.get(target)
        if defect
        in ("not_a_number", "out_of_range", "time_not_increasing", "ragged_short", "ragged_long", "separator_row")
        else None
    )
    if defect in ("header_missing", "header_extra", "header_duplicate", "header_blank"):
        row = 1
    return data, expected, defect, row


@settings(FUZZ, max_examples=200)
@given(csv_cases())
def test_csv_logs_are_read_exactly_or_refused_with_file_and_row(case):
    """Valid files (any dress) read back exactly; each single defect is refused, naming the row."""
    count("csv")
    data, expected, defect, row = case
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.csv"
        path.write_bytes(data)
        log = read_or_error(path)
    if defect is None:
        assert log is not None, data
        np.testing.assert_array_equal(np.column_stack([log.time, log.states, log.actions]), expected)
        return
    assert log is None, f"defect {defect} accepted: {data!r}"
    if row is not None:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "log.csv"
            path.write_bytes(data)
            with pytest.raises(LogError, match=rf": row {row}: "):
                read_log(path)


CELL_SOUP = st.one_of(
    st.sampled_from(
        [
            "0",
            "1",
            "40",
            "-30",
            "1e308",
            "99.5",
            "101",
            '"',
            '""',
            "time",
            "color",
            "angle",
            " ",
            "\t",
            "\x00",
            "\ufeff",
            "\u0660",
        ]
    ),
    NOT_A_NUMBER,
    st.integers(-(10**20), 10**20).map(str),
    st.floats().map(repr),
)


@settings(FUZZ, max_examples=120)
@given(
    st.one_of(
        st.binary(max_size=300),
        st.lists(st.lists(CELL_SOUP, max_size=5).map(",".join), max_size=8).map(
            lambda ls: ("time,color,angle\n" + "\n".join(ls)).encode("utf-8", "surrogatepass")
        ),
    )
)
def test_random_bytes_never_crash_or_pass_bad_values(data):
    """Arbitrary bytes and cell soups: a log that keeps the contract, or one clean error line."""
    count("bytes")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "soup.csv"
        path.write_bytes(data)
        read_or_error(path)


# ----------------------------------------------------------------------------- sidecars

JSON_LEAVES = st.one_of(st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(), st.text(max_size=10))
JSON_VALUES = st.recursive(
    JSON_LEAVES, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4), max_leaves=12
)
GOOD_META = LogMeta(controller={"name": "lane-keeping", "params": {"x": 30}}, period_ms=40.0, run_id="r1").to_json()
SIDECAR_PATHS = [
    ("schema_version",),
    ("states",),
    ("actions",),
    ("logged",),
    ("controller",),
    ("controller", "name"),
    ("controller", "params"),
    ("controller", "params", "x"),
    ("period_ms",),
    ("run_id",),
    ("source",),
    ("provenance",),
    ("states", 0),
    ("states", 0, "name"),
    ("states", 0, "range"),
    ("states", 0, "range", 1),
    ("states", 0, "unit"),
    ("states", 0, "resolution"),
    ("states", 0, "saturates"),
    ("actions", 0, "name"),
]
RUN_IDS = st.sampled_from(["../x", "/etc/passwd", "a/b", ".hidden", "", "x" * 200, "con\n", "ok-1", "a\\b", ".."])


def mutated(base: dict[str, Any], paths: list[tuple[Any, ...]], draw: st.DrawFn) -> Any:
    """``base`` with one field (at any depth) replaced by arbitrary JSON or deleted."""
    doc = json.loads(json.dumps(base))
    path = draw(st.sampled_from(paths))
    node = doc
    for k in path[:-1]:
        node = node[k]
    choice = draw(st.integers(0, 9))
    if isinstance(node, dict) and choice == 0:
        node.pop(path[-1], None)
    elif choice == 1:
        node[path[-1]] = DEEP  # replaced by a deeply nested list in the text (json.dumps would recurse)
    else:
        node[path[-1]] = draw(RUN_IDS if path[-1] == "run_id" else JSON_VALUES)
    return doc


DEEP = "\u2603deep\u2603"


@st.composite
def json_texts(draw: st.DrawFn, base: dict[str, Any], paths: list[tuple[Any, ...]]) -> str:
    kind = draw(st.integers(0, 5))
    if kind == 0:
        return json.dumps(draw(JSON_VALUES))
    if kind == 1:
        depth = draw(st.sampled_from([40, 500, 5000, 200_000]))
        opener, closer = draw(st.sampled_from([("[", "]"), ('{"a":', "}")]))
        return opener * depth + "1" + closer * depth
    if kind == 2:
        return draw(st.text(max_size=40))
    text = json.dumps(mutated(base, paths, draw))
    depth = draw(st.sampled_from([40, 900, 3000]))
    return text.replace(json.dumps(DEEP), "[" * depth + "1" + "]" * depth)


@settings(FUZZ, max_examples=120)
@given(json_texts(GOOD_META, SIDECAR_PATHS))
def test_sidecars_of_any_shape_are_read_or_refused_and_can_be_skipped(text):
    """A sidecar of the wrong type, shape or depth is one error naming it, and --skip-bad skips it."""
    count("sidecar")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        bad = folder / "a_run.csv"
        bad.write_text(GOOD_CSV)
        sidecar_path(bad).write_text(text)
        log = read_or_error(bad, sidecar_path(bad))
        if log is not None:
            assert log.meta.run_id is None or re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9._-]*", log.meta.run_id)
            assert log.meta.period_ms is None or (math.isfinite(log.meta.period_ms) and log.meta.period_ms > 0)
            return
        (folder / "b_good.csv").write_text(GOOD_CSV)
        with deadline(), warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            logs = load_logs(folder, skip_bad=True)
        assert [lg.name for lg in logs] == ["b_good.csv"]
        assert any(str(sidecar_path(bad)) in str(w.message) or str(bad) in str(w.message) for w in caught)


# ----------------------------------------------------------------------------- manifests

GOOD_MANIFEST = {"system": LANE.to_json(), "logs": ["log.csv"]}
MANIFEST_PATHS = [
    ("system",),
    ("logs",),
    ("logs", 0),
    ("system", "name"),
    ("system", "period_ms"),
    ("system", "schema"),
    ("system", "schema", "states"),
    ("system", "schema", "states", 0, "range"),
    ("system", "schema", "actions", 0, "name"),
    ("system", "versions"),
    ("system", "versions", "pattern"),
    ("system", "versions", "params"),
    ("system", "versions", "map"),
    ("system", "controller"),
    ("system", "controller", "params"),
    ("system", "ignore"),
    ("system", "preset"),
    ("system", "goals"),
    ("system", "requirements"),
    ("system", "requirements", 0),
    ("system", "requirements", 0, "probability"),
]
LISTED = st.lists(
    st.sampled_from(
        ["log.csv", "missing.csv", "sub", "fifo.csv", "/dev/zero", "../log.csv", "zero.csv", "log.meta.json"]
    ),
    min_size=1,
    max_size=3,
)


@settings(FUZZ, max_examples=100)
@given(json_texts(GOOD_MANIFEST, MANIFEST_PATHS), st.one_of(st.none(), LISTED))
def test_manifests_of_any_shape_are_read_or_refused(text, listed):
    """Manifests of any shape, listing files that are missing, folders, FIFOs or /dev/zero."""
    count("manifest")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "log.csv").write_text(GOOD_CSV)
        (folder / "sub").mkdir()
        os.mkfifo(folder / "fifo.csv")
        (folder / "zero.csv").symlink_to("/dev/zero")
        if listed is not None:
            try:
                doc = json.loads(text)
            except (ValueError, RecursionError):
                doc = None
            if isinstance(doc, dict):
                doc["logs"] = listed
                text = json.dumps(doc)
        manifest = folder / "m.json"
        manifest.write_text(text)
        try:
            with deadline():
                system, files = load_manifest(manifest)
                logs = load_logs(manifest)
        except LogError as exc:
            assert_clean_error(exc, manifest, folder, "/dev/zero")
            return
        columns = (system or LANE).schema.columns
        for lg in logs:
            assert_contract(lg, columns)


# ----------------------------------------------------------------------------- file-name patterns

BRACE_SOUP = st.lists(
    st.sampled_from(list("{}_xyrun.0-9ä ") + ["{x}", "{run}", "{0}", "{x-y}", "log_", ".csv", "{{", "}}", "{y}"]),
    max_size=12,
).map("".join)


@settings(FUZZ, max_examples=80)
@given(BRACE_SOUP)
def test_file_name_patterns_compile_or_are_refused(pattern):
    """A brace soup is a regex with one group per field or a ValueError naming the pattern, and a
    whole command line with it exits 0 or 2 with one line."""
    count("pattern")
    try:
        rx = pattern_regex(pattern)
    except ValueError as exc:
        assert_clean_error(exc, repr(pattern), "pattern")
    else:
        assert set(rx.groupindex) == set(re.findall(r"\{(\w+)\}", pattern))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name in ("log_30_0.csv", "log_30_1.csv", "log_nan_2.csv", "log_1e999_3.csv", "log_\u0661_4.csv"):
            (folder / name).write_text(GOOD_CSV)
        code, err = run_cli(["split", "--logs", str(folder), f"--pattern={pattern}", "--out", str(folder / "out")])
    if code != 0:
        assert_cli_error(code, err, "split")


def test_non_finite_or_foreign_version_fields_are_refused(tmp_path):
    """``log_nan_0.csv`` never makes a controller with x = NaN; digits must be ASCII to count."""
    system = LANE.with_pattern("log_{x}_{run}.csv")
    for name in ("log_nan_0.csv", "log_-inf_0.csv", "log_1e999_0.csv"):
        (tmp_path / name).write_text(GOOD_CSV)
        with pytest.raises(LogError, match="not a finite number"):
            load_logs(tmp_path / name, system)
    (tmp_path / "log_\u0661_0.csv").write_text(GOOD_CSV)
    assert load_logs(tmp_path / "log_\u0661_0.csv", system)[0].param["x"] == "\u0661"


# ----------------------------------------------------------------------------- system descriptions (TOML)


def to_toml(doc: dict[str, Any]) -> str:
    """A TOML document from nested data: top-level values, then tables and arrays of tables."""
    lines = [
        f"{json.dumps(k)} = {toml_value(v)}"
        for k, v in doc.items()
        if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(e, dict) for e in v))
    ]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += [f"[{json.dumps(k)}]"] + [f"{json.dumps(kk)} = {toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and all(isinstance(e, dict) for e in v):
            for e in v:
                lines += [f"[[{json.dumps(k)}]]"] + [f"{json.dumps(kk)} = {toml_value(vv)}" for kk, vv in e.items()]
    return "\n".join(lines) + "\n"


def toml_docs() -> list[dict[str, Any]]:
    import tomllib

    return [tomllib.loads(p.read_text()) for p in shipped().values()]


TOML_LEAVES = st.one_of(st.booleans(), st.integers(-(10**18), 10**18), st.floats(), st.text(max_size=8))
TOML_VALUES = st.recursive(
    TOML_LEAVES,
    lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text("abcxyz_", min_size=1, max_size=5), c, max_size=3),
    max_leaves=8,
)
TOML_KEYS = [
    "name",
    "role",
    "range",
    "unit",
    "resolution",
    "saturates",
    "pattern",
    "params",
    "map",
    "period_ms",
    "goals_preset",
    "expr",
    "probability",
    "kind",
    "metric",
    "signal",
]


@st.composite
def toml_texts(draw: st.DrawFn) -> str:
    docs = toml_docs()
    doc = json.loads(json.dumps(draw(st.sampled_from(docs))))
    for _ in range(draw(st.integers(1, 3))):
        table = draw(st.sampled_from(sorted(doc)))
        node = doc[table]
        if isinstance(node, list) and node:
            node = node[draw(st.integers(0, len(node) - 1))]
        if isinstance(node, dict):
            node[draw(st.sampled_from(TOML_KEYS + sorted(node)))] = draw(TOML_VALUES)
        else:
            doc[table] = draw(TOML_VALUES)
    if draw(st.integers(0, 7)) == 0:
        doc[draw(st.sampled_from(["system", "signals", "versions", "controller", "goals", "requirements"]))] = draw(
            TOML_VALUES
        )
    try:
        return to_toml(doc)
    except TypeError:
        return draw(st.text(max_size=60))


@settings(FUZZ, max_examples=120)
@given(st.one_of(toml_texts(), st.text(max_size=80)))
def test_system_descriptions_are_valid_or_refused(text):
    """A mutated shipped description (or TOML noise) is a self-consistent description or one error
    line naming its file; an accepted one also routes version fields without crashing."""
    count("toml")
    where = "fuzzed.toml"
    try:
        desc = SystemDescription.from_toml_text(text, where)
    except ValueError as exc:
        assert_clean_error(exc, where)
        return
    check_description(desc)
    back = SystemDescription.from_json(json.loads(json.dumps(desc.to_json())), where)
    assert back.schema == desc.schema and back.versions == desc.versions
    try:
        desc.controller_for({p: 1 for p in desc.versions.params})
    except ValueError as exc:
        assert "\n" not in str(exc)
    if desc.versions.pattern is None and desc.schema.columns == LANE.schema.columns:
        with tempfile.TemporaryDirectory() as tmp:  # the fuzzed ranges, saturation and ignores, applied
            path = Path(tmp) / "log.csv"
            path.write_text(GOOD_CSV)
            try:
                with deadline():
                    logs = load_logs(path, desc)
            except LogError as exc:
                assert_clean_error(exc, path)
            else:
                assert_contract(logs[0], desc.schema.columns)


def check_description(desc: SystemDescription) -> None:
    names = desc.schema.columns + list(desc.ignore)
    assert desc.schema.states and desc.schema.actions
    assert len(set(names)) == len(names) and "time" not in names[1:]
    for ch in desc.schema.channels + desc.schema.logged:
        assert COLUMN_NAME.match(ch.name) and ch.low < ch.high
        assert isinstance(ch.unit, str) and isinstance(ch.saturates, bool)
    assert desc.period_ms is None or (math.isfinite(desc.period_ms) and desc.period_ms > 0)
    assert all(isinstance(p, str) for p in desc.versions.params)
    assert all(isinstance(k, str) and isinstance(v, str) for k, v in desc.versions.map.items())
    if desc.versions.pattern is not None:
        pattern_regex(desc.versions.pattern)
    assert desc.preset is None or isinstance(desc.preset, str)
    assert all(0 < r.probability < 1 for r in desc.requirements)


@settings(FUZZ, max_examples=60)
@given(
    json_texts(
        LANE.to_json(),
        [(k,) for k in LANE.to_json()]
        + [("schema", "states", 0, "range"), ("versions", "params"), ("versions", "map"), ("versions", "pattern")],
    )
)
def test_recorded_descriptions_are_valid_or_refused(text):
    """The JSON form recorded in checkpoints and manifests, fuzzed the same way."""
    count("system-json")
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError):
        return
    try:
        desc = SystemDescription.from_json(doc, "recorded")
    except ValueError as exc:
        assert_clean_error(exc, "recorded")
        return
    check_description(desc)


# ----------------------------------------------------------------------------- hangs: FIFOs, devices, huge files


@pytest.mark.parametrize("kind", ["fifo", "dev-zero-link", "dev-null-link", "folder", "dangling-link"])
@pytest.mark.parametrize("role", ["log", "sidecar", "manifest"])
def test_special_files_are_refused_without_hanging(tmp_path, kind, role):
    count("special")
    target = {"log": tmp_path / "x.csv", "sidecar": tmp_path / "x.meta.json", "manifest": tmp_path / "m.json"}[role]
    if role != "log":
        (tmp_path / "x.csv").write_text(GOOD_CSV)
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "folder":
        target.mkdir()
    else:
        target.symlink_to(
            {"dev-zero-link": "/dev/zero", "dev-null-link": "/dev/null", "dangling-link": tmp_path / "nowhere"}[kind]
        )
    source = target if role == "manifest" else tmp_path / "x.csv"
    with deadline(), pytest.raises(LogError) as err:
        load_logs(source)
    assert_clean_error(err.value, target, source)


def test_huge_inputs_are_read_or_refused_in_time(tmp_path):
    """A 25 MB log of valid rows reads in time; a 2 MB sidecar is refused by size, not parsed."""
    count("special")
    big = tmp_path / "big.csv"
    n = 1_000_000
    with open(big, "w") as fh:
        fh.write("time,color,angle\n")
        fh.writelines(f"{i * 40},{i % 100},30\n" for i in range(n))
    with deadline(60):
        assert len(read_log(big)) == n
    side = tmp_path / "s.csv"
    side.write_text(GOOD_CSV)
    sidecar_path(side).write_text('{"pad": "' + "x" * (2 << 20) + '"}')
    with deadline(), pytest.raises(LogError, match="larger than"):
        read_log(side)


# ----------------------------------------------------------------------------- command lines


@pytest.fixture(scope="module")
def log_folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        rng = np.random.default_rng(0)
        for x in (30, 50):
            for run in range(3):
                color = rng.integers(0, 100, 30)
                rows = "".join(f"{i * 40},{c},{x if c > 40 else -x}\n" for i, c in enumerate(color))
                (folder / f"log_{x}_{run}.csv").write_text("time,color,angle\n" + rows)
        yield folder


BAD_INTS = st.sampled_from(["-5", "-1", "0", "1.5", "1e3", "nan", "", "abc", "0x10", "--"])
ANY_INTS = st.one_of(BAD_INTS, st.sampled_from(["1", "2", "3", str(10**12)]))


@st.composite
def bad_command_lines(draw: st.DrawFn, folder: Path, out: Path) -> tuple[str, list[str]]:
    """A command line with at least one argument the command must refuse before doing any work."""
    cmd = draw(st.sampled_from(["split", "train", "simulate", "verify", "init"]))
    logs = draw(st.sampled_from([str(folder), str(folder / "missing"), str(folder / "log_30_0.csv"), "/dev/zero"]))
    if cmd == "split":
        flag = draw(st.sampled_from(["--train", "--val", "--test"]))
        value = draw(st.sampled_from(["-1", "-5", "1.5", "abc", "", str(10**12)]))
        return cmd, ["split", "--logs", logs, flag, value, "--out", str(out)]
    if cmd == "train":
        flag = draw(st.sampled_from(["--epochs", "--history", "--eval-every", "--hidden"]))
        value = draw(
            st.sampled_from(
                ["0", "-1", "1.5", "abc", "0,8", "8,-1"]
                if flag == "--hidden"
                else ["0", "-1", "-5", "1.5", "1e3", "nan", "abc"]
            )
        )
        return cmd, ["train", "--logs", logs, f"{flag}={value}", "--quiet", "-o", str(out / "m.pt")]
    if cmd == "simulate":
        model = draw(
            st.sampled_from([str(folder / "missing.pt"), str(folder / "log_30_0.csv"), "/dev/zero", str(folder)])
        )
        extra = draw(
            st.sampled_from(
                [
                    [],
                    ["--runs", "0"],
                    ["--runs", "-1"],
                    ["--steps", "-5"],
                    ["--steps", "1e12"],
                    ["--steps", str(10**12)],
                    ["--runs", "1.5"],
                ]
            )
        )
        return cmd, ["simulate", "--model", model, "--init-logs", logs, *extra, "--out", str(out)]
    if cmd == "verify":
        sim = draw(st.sampled_from([str(folder / "missing"), "/dev/zero", str(folder / "m.json")]))
        extra = draw(st.sampled_from([[], ["--skip", "-1"], ["--skip", "1.5"], ["--skip", str(10**12)]]))
        return cmd, ["verify", "--real", logs, "--sim", sim, *extra]
    target = draw(st.sampled_from([str(folder / "missing"), str(folder / "log_30_0.csv"), "/dev/zero"]))
    pattern = draw(st.sampled_from([[], ["--pattern", "log_{x}_{x}.csv"], ["--pattern", "{"], ["--pattern", "{0}"]]))
    return cmd, ["init", "--logs", target, *pattern, "-o", str(out / "s.toml")]


def test_command_lines_with_bad_arguments_exit_2_with_one_line(log_folder, tmp_path):
    """Every generated bad command line: exit 2, one stderr line ``envi <cmd>: error: ...``.

    Values argparse itself refuses (``--epochs 1.5``) are checked apart: argparse prints its usage
    before the error line, which is cli.py's to change (see the report), so only their exit code and
    last line are asserted there."""
    out = tmp_path / "out"

    @settings(FUZZ, max_examples=90)
    @given(bad_command_lines(log_folder, out))
    def run(case: tuple[str, list[str]]) -> None:
        count("cli")
        cmd, argv = case
        code, err = run_cli(argv)
        if err.startswith("usage:"):
            assert code == 2 and err.strip().splitlines()[-1].startswith(f"envi {cmd}: error: argument"), err
            return
        assert_cli_error(code, err, cmd)

    run()


@settings(FUZZ, max_examples=60)
@given(csv_cases())
def test_init_drafts_what_reads_back_or_refuses(case):
    """envi init on any generated log: a draft that loads and reads that log, or one error line."""
    count("init")
    data, expected, _, _ = case
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "logs"
        folder.mkdir()
        (folder / "run.csv").write_bytes(data)
        out = Path(tmp) / "system.toml"
        code, err = run_cli(["init", "--logs", str(folder), "-o", str(out)])
        if code != 0:
            assert_cli_error(code, err, "init")
            assert expected is None, f"a valid log refused: {err}"
            return
        logs = load_logs(folder, SystemDescription.load(out))
        assert_contract(logs[0])
        if expected is not None:
            assert logs[0].time.tolist() == expected[:, 0].tolist()


def test_init_drafts_a_description_that_reads_its_logs(log_folder, tmp_path):
    out = tmp_path / "system.toml"
    code, err = run_cli(["init", "--logs", str(log_folder), "-o", str(out)])
    assert code == 0, err
    desc = SystemDescription.load(out)
    assert desc.schema.columns == ["time", "color", "angle"] and desc.versions.pattern == "log_{v1}_{run}.csv"
    assert len(load_logs(log_folder, desc)) == 6


@pytest.mark.parametrize(
    "body, why",
    [
        ("time,color,angle\n0,1,2\n40,nan,2\n", "row 3: column 'color'"),
        ("time,color,angle\n0,1,2\n40,\u0661,2\n", "row 3: column 'color'"),
        ("time,color,angle\n0,1,2\n0,1,2\n", "row 3: time 0 does not increase"),
        ("time,color,angle,color\n0,1,2,3\n", "appear twice"),
        ("time\n0\n", "besides 'time'"),
        ("time,color,angle\n0,-1e308,1e308\n40,1e308,-1e308\n", None),
    ],
)
def test_init_reads_logs_as_strictly_as_read_log(tmp_path, body, why):
    """envi init once took 'nan', Arabic digits and overflowing ranges; now each is one line (or,
    for values at the float limit, a draft that reads back)."""
    count("init")
    folder = tmp_path / "logs"
    folder.mkdir()
    (folder / "a.csv").write_text(body)
    code, err = run_cli(["init", "--logs", str(folder), "-o", str(tmp_path / "s.toml")])
    if why is None:
        assert code == 0, err
        SystemDescription.load(tmp_path / "s.toml")
        return
    assert_cli_error(code, err, "init")
    assert why in err and str(folder / "a.csv") in err


# ----------------------------------------------------------------------------- the count


def test_zz_at_least_400_generated_inputs():
    """Issue 16 asks for at least 400 generated malformed inputs; this counts what ran above."""
    expected = {"csv", "bytes", "sidecar", "manifest", "pattern", "toml", "system-json", "special", "cli", "init"}
    if set(GENERATED) != expected:
        pytest.skip(f"only part of the module ran ({sorted(GENERATED)})")
    parts = ", ".join(f"{k} {v}" for k, v in sorted(GENERATED.items()))
    print(f"generated inputs: {sum(GENERATED.values())} ({parts})")
    assert sum(GENERATED.values()) >= MIN_TOTAL, GENERATED

"""Field and simulated logs: one CSV per run plus an optional ``<name>.meta.json`` sidecar.

A log is ``time`` in milliseconds, then the state columns, the action columns and any logged-only
columns (a PID's internal terms, say) its system description declares. Real field-test (FOT) logs,
twin logs, hardware-in-the-loop logs and simulated traces are all written and read through this
module, so every downstream tool treats them alike. The reader is strict: every problem is reported
with the file (and row and column where there is one), because a silently mangled log poisons
every model trained on it. Which controller version made a log (its :class:`ControllerSpec`) is
read here too, from the sidecar or from the file name through the system description, and logs are
grouped by it here, once.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import math
import os
import re
import shutil
import tempfile

import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import atomic_write_text
from .controllers import REGISTRY, ControllerSpec, finite_numbers
from .files import parse_json, regular_file
from .system import Channel, LogSchema, SystemDescription, describe_schema, lane_keeping, pattern_regex

__all__ = ["Channel", "LogSchema", "pattern_regex"]

SCHEMA_VERSION = 1
SOURCES = ("fot", "sim", "twin", "hil")
SIMULATED_SOURCES = ("sim", "hil")  # the learnt model made the readings (in hil, for the real controller)
#: Run ids become file names: letters, digits, '.', '_' and '-', not starting with a dot.
RUN_ID = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,119}$")
MAX_SIDECAR_BYTES = 1 << 20


class LogError(ValueError):
    """A log file (or a set of logs) that cannot be used; the message names file and row."""


#: The lane-keeping robot: a reflected-light colour reading (0 = black, 100 = white) and a
#: steering angle in degrees, as its shipped system description declares them.
LANE_KEEPING_SCHEMA = lane_keeping().schema


def safe_run_id(value: Any, where: str) -> str:
    """A run id that is safe as a file name (no path, no traversal); anything else is an error."""
    text = str(value)
    if isinstance(value, (dict, list, bool)) or value is None or not RUN_ID.match(text):
        raise LogError(f"{where}: run_id {text[:60]!r} is not a plain name (letters, digits, '.', '_', '-')")
    return text


#: every key a sidecar may hold: what :meth:`LogMeta.to_json` writes
SIDECAR_KEYS = frozenset(
    {
        "schema_version",
        "states",
        "actions",
        "logged",
        "controller",
        "period_ms",
        "run_id",
        "source",
        "provenance",
        "breaks",
    }
)


@dataclass
class LogMeta:
    """What the sidecar records. Everything but the schema is optional for a field log."""

    schema: LogSchema = LANE_KEEPING_SCHEMA
    controller: dict[str, Any] | None = None  # ControllerSpec.to_json()
    period_ms: float | None = None
    run_id: str | None = None
    source: str = "fot"
    provenance: dict[str, Any] = field(default_factory=dict)
    #: rows that do not follow the row before them, because rows are missing between the two (a frame
    #: lost on the collector's link, a tick the brick skipped or never sent): no model window may span
    #: one. Sorted, each in 1..rows-1.
    breaks: tuple[int, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "schema_version": SCHEMA_VERSION,
            **self.schema.to_json(),
            "controller": self.controller,
            "period_ms": self.period_ms,
            "run_id": self.run_id,
            "source": self.source,
            "provenance": self.provenance,
            **({"breaks": list(self.breaks)} if self.breaks else {}),
        }

    @staticmethod
    def from_json(d: Any, where: str) -> LogMeta:
        """A sidecar's content, every field checked for its type: a wrong one is a LogError."""
        if not isinstance(d, dict):
            raise LogError(f"{where}: a sidecar must be a JSON object, not {type(d).__name__}")
        unknown = sorted(set(d) - SIDECAR_KEYS, key=str)
        if unknown:  # a misspelt 'period' or 'runid' would otherwise be dropped without a word
            raise LogError(
                f"{where}: sidecar key(s) {', '.join(repr(k)[:40] for k in unknown[:3])} unknown; "
                f"known: {', '.join(sorted(SIDECAR_KEYS))}"
            )
        version = d.get("schema_version")
        if isinstance(version, bool) or not isinstance(version, int) or version != SCHEMA_VERSION:
            raise LogError(
                f"{where}: sidecar schema_version {version!r:.40} is not supported (expected {SCHEMA_VERSION})"
            )
        source = d.get("source", "fot")
        if source not in SOURCES:
            raise LogError(f"{where}: sidecar source {source!r:.40} is not one of {', '.join(SOURCES)}")
        try:
            schema = LogSchema.from_json(d)
            spec = None if d.get("controller") is None else ControllerSpec.from_json(d["controller"])
            controller = None if spec is None else spec.to_json()
            if spec is not None:
                finite_numbers(spec.params, "controller params")
                _no_numbers_as_text(spec.params)
                if spec.name in REGISTRY:  # built here: a bad gain stops the read, not a training's end
                    spec.build(len(schema.states), len(schema.actions))
        except ValueError as exc:
            raise LogError(f"{where}: sidecar {exc}") from None
        period = d.get("period_ms")
        if period is not None and (
            isinstance(period, bool)
            or not isinstance(period, (int, float))
            or not (math.isfinite(period) and period > 0)
        ):
            raise LogError(f"{where}: sidecar period_ms {period!r:.40} is not a positive number")
        run_id = None if d.get("run_id") is None else safe_run_id(d["run_id"], where)
        provenance = {} if d.get("provenance") is None else d["provenance"]
        if not isinstance(provenance, dict):
            raise LogError(f"{where}: sidecar provenance must be an object")
        breaks = [] if d.get("breaks") is None else d["breaks"]
        if (
            not isinstance(breaks, list)
            or any(isinstance(b, bool) or not isinstance(b, int) or b < 1 for b in breaks)
            or any(b >= c for b, c in zip(breaks, breaks[1:]))
        ):
            raise LogError(f"{where}: sidecar breaks {breaks!r:.60} is not an increasing list of row numbers >= 1")
        return LogMeta(
            schema=schema,
            controller=controller,
            period_ms=None if period is None else float(period),
            run_id=run_id,
            source=source,
            provenance=dict(provenance),
            breaks=tuple(breaks),
        )


def _no_numbers_as_text(params: dict[str, Any]) -> None:
    """A ValueError for a sidecar controller parameter written as text that reads as a number
    (``"x": "30"``): the controller took it, but its version was never x = 30 (a verification
    found no real runs of it)."""
    stack: list[tuple[str, Any]] = list(params.items())
    while stack:
        key, value = stack.pop()
        if isinstance(value, str) and _NUMBER.match(value.strip()):
            raise ValueError(f"controller parameter {key!r} is the text {value[:40]!r}; write the number itself")
        if isinstance(value, dict):
            stack.extend((f"{key}.{k}", v) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((f"{key}.{i}", v) for i, v in enumerate(value))


@dataclass
class Log:
    """One run: time in ms (shape T), states (T, |s|), actions (T, |a|), its metadata, and the
    logged-only columns the schema declares (T, n_logged), which travel with it unmodelled."""

    path: Path | None
    time: np.ndarray
    states: np.ndarray
    actions: np.ndarray
    meta: LogMeta
    logged: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.logged is None:
            self.logged = np.zeros((len(self.time), 0))

    @property
    def name(self) -> str:
        return self.path.name if self.path is not None else (self.meta.run_id or "<memory>")

    def __len__(self) -> int:
        return int(self.time.shape[0])

    @property
    def values(self) -> np.ndarray:
        """States and actions side by side, (T, |s|+|a|): the layout of a model window."""
        return np.concatenate([self.states, self.actions], axis=1)

    @property
    def param(self) -> dict[str, Any]:
        """Controller parameters (empty when unknown)."""
        return dict((self.meta.controller or {}).get("params", {}))

    @property
    def controller(self) -> ControllerSpec:
        """The controller version that produced this log; an error when the log does not say."""
        if not self.meta.controller:
            raise LogError(
                f"{self.name}: the log does not say which controller produced it (give a "
                "system description with a [controller], or a file-name --pattern with its version)"
            )
        return ControllerSpec.from_json(self.meta.controller)

    def signal(self, name: str) -> np.ndarray:
        """One column by name: a state, an action or a logged-only column, (T,)."""
        schema = self.meta.schema
        for arr, chans in ((self.states, schema.states), (self.actions, schema.actions), (self.logged, schema.logged)):
            for i, c in enumerate(chans):
                if c.name == name:
                    return arr[:, i]
        raise KeyError(f"{self.name}: no signal {name!r}; it has {', '.join(schema.columns[1:])}")

    def sha256(self) -> str:
        """Hash of the numeric content, so a checkpoint can name exactly what it was trained on."""
        h = hashlib.sha256()
        for arr in (self.time, self.states, self.actions):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        return h.hexdigest()


def read_json(path: Path, what: str) -> Any:
    """A sidecar or manifest's JSON: a regular file of at most 1 MiB, UTF-8 (BOM allowed), no NaN,
    at most files.MAX_DEPTH deep, no integer beyond a float; anything else is a LogError naming the file."""
    _regular_file(path)
    if path.stat().st_size > MAX_SIDECAR_BYTES:
        raise LogError(f"{path}: {what} larger than {MAX_SIDECAR_BYTES >> 20} MiB")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise LogError(f"{path}: cannot read {what} ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise LogError(f"{path}: {what} is not valid JSON ({exc})") from None
    return parse_json(text, str(path), what, LogError)


def sidecar_path(csv_path: Path) -> Path:
    return csv_path.with_name(csv_path.stem + ".meta.json")


def _regular_file(path: Path) -> None:
    """Refuse FIFOs, devices and links to them before opening: reading one would hang or never end."""
    regular_file(path, "a log", LogError)


def read_sidecar(side: Path) -> LogMeta:
    return LogMeta.from_json(read_json(side, "sidecar"), str(side))


_NUMBER = re.compile(r"^[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?$")  # ASCII digits only


def _parse_cell(text: str, path: Path, row: int, col: str) -> float:
    if not _NUMBER.match(text):
        low = text.lower().lstrip("+-")
        if low in ("nan", "inf", "infinity"):
            raise LogError(f"{path}: row {row}: column '{col}' is {text!r} (NaN/inf are not valid readings)")
        raise LogError(f"{path}: row {row}: column '{col}' has non-numeric value {text!r}")
    value = float(text)
    if not math.isfinite(value):
        raise LogError(f"{path}: row {row}: column '{col}' is {text!r} (out of the float range)")
    return value


def _read_text(path: Path) -> str:
    """A CSV file's text with line ends made ``\\n``: a regular UTF-8 file (BOM allowed), no NUL."""
    _regular_file(path)
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            text = fh.read().replace("\r\n", "\n").replace("\r", "\n")
    except OSError as exc:
        raise LogError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise LogError(f"{path}: not a UTF-8 text CSV file ({exc.reason} at byte {exc.start})") from None
    if "\x00" in text:
        raise LogError(f"{path}: not a text CSV file (it holds NUL bytes)")
    return text


def _header_names(path: Path, text: str) -> list[str]:
    """The header row's names; empty, repeated or blank names are errors on row 1."""
    first = text.split("\n", 1)[0]
    try:
        header = [h.strip() for h in next(csv.reader([first]))] if first.strip() else []
    except csv.Error as exc:
        raise LogError(f"{path}: row 1: not a valid CSV header ({exc})") from None
    if not header:
        raise LogError(f"{path}: empty file (no header row)")
    blank = [i + 1 for i, h in enumerate(header) if not h]
    if blank:
        raise LogError(f"{path}: row 1: column {blank[0]} of the header has no name")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise LogError(f"{path}: row 1: column(s) {', '.join(dup)} appear twice in the header")
    return header


def read_columns(path: str | os.PathLike) -> list[str]:
    """The column names a CSV log's header declares (checked as :func:`read_log` checks them)."""
    path = Path(path)
    return _header_names(path, _read_text(path))


def _header(path: Path, text: str, expected: list[str], ignore: Sequence[str]) -> tuple[list[str], list[int]]:
    header = _header_names(path, text)
    missing = [c for c in expected if c not in header]
    extra = [c for c in header if c not in expected and c not in ignore]
    if missing or extra:
        parts = []
        if missing:
            parts.append("missing column(s) " + ", ".join(missing))
        if extra:
            parts.append(
                "unexpected column(s) " + ", ".join(extra) + " (declare them in the system description "
                "with role 'logged' or 'ignore')"
            )
        raise LogError(f"{path}: row 1: {'; '.join(parts)} (expected {','.join(expected)})")
    return header, [header.index(c) for c in expected]


def _parse_rows(
    path: Path, text: str, header: list[str], order: list[int], expected: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """The data rows as floats in ``expected`` order, and each one's row number in the file (blank
    lines count, as a spreadsheet shows them). A fast vectorised parse for well-formed files without
    blank lines; anything else is read row by row so an error names the row and column."""
    body = text.split("\n", 1)[1] if "\n" in text else ""
    if text.isascii() and "\n\n" not in body and not body.startswith("\n"):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # an empty file body warns; treat it as the slow path
                data = np.loadtxt(
                    io.StringIO(body), delimiter=",", dtype=np.float64, comments=None, ndmin=2, quotechar='"'
                )
            if data.shape[1] == len(header) and np.isfinite(data).all():
                return data[:, order], np.arange(2, 2 + len(data))
        except (ValueError, UserWarning):
            pass
    data_rows, numbers = [], []
    reader = csv.reader(io.StringIO(body))
    for row in reader:
        i = reader.line_num + 1  # the line a row ends on; the header is line 1
        if not row:
            continue  # a blank line is not a reading
        if all(not c.strip() for c in row):
            raise LogError(f"{path}: row {i}: an empty row (only separators)")
        if len(row) != len(header):
            raise LogError(f"{path}: row {i}: {len(row)} cells, header has {len(header)}")
        data_rows.append([_parse_cell(row[j].strip(), path, i, expected[k]) for k, j in enumerate(order)])
        numbers.append(i)
    return np.array(data_rows, dtype=np.float64).reshape(len(data_rows), len(order)), np.array(numbers, dtype=int)


def _check_ranges(path: Path, data: np.ndarray, rows: np.ndarray, schema: LogSchema) -> np.ndarray:
    """Declared valid ranges, enforced: a sensor that saturates is clipped at its range, any other
    value outside it is an error naming row, column and range (one 1e308 poisons a model)."""
    for k, ch in enumerate(schema.channels + schema.logged, start=1):
        col = data[:, k]
        bad = np.flatnonzero((col < ch.low) | (col > ch.high))
        if not bad.size:
            continue
        if ch.saturates:
            data[:, k] = np.clip(col, ch.low, ch.high)
            continue
        r = int(bad[0])
        raise LogError(
            f"{path}: row {rows[r]}: column '{ch.name}' is {col[r]:g}, outside its valid range "
            f"[{ch.low:g}, {ch.high:g}]"
        )
    return data


def read_log(
    path: str | os.PathLike, meta: LogMeta | None = None, min_length: int = 1, ignore: Sequence[str] = ()
) -> Log:
    """Read and validate one CSV log.

    ``meta`` describes a log that has no sidecar (e.g. the real lane-keeping logs); a sidecar, when
    present, wins (:func:`load_logs` checks that the two agree). ``ignore`` names columns that may be
    present and are dropped. ``min_length`` is the history window: a shorter log cannot give one
    training pair. UTF-8 with or without BOM and CRLF line ends are read as is. Row numbers in
    errors count the header as row 1, as a spreadsheet shows them.
    """
    path = Path(path)
    side = sidecar_path(path)
    if side.exists() or side.is_symlink():
        meta = read_sidecar(side)
    meta = meta or LogMeta()
    expected = meta.schema.columns
    text = _read_text(path)
    header, order = _header(path, text, expected, ignore)
    try:
        data, rows = _parse_rows(path, text, header, order, expected)
    except csv.Error as exc:
        raise LogError(f"{path}: not a valid CSV file ({exc})") from None
    n = data.shape[0]
    if n == 0:
        raise LogError(f"{path}: no data rows (only a header)")
    if n < min_length:
        raise LogError(f"{path}: {n} data rows, shorter than the {min_length} the history window needs")
    dt = np.diff(data[:, 0])
    bad = np.nonzero(dt <= 0)[0]
    if bad.size:
        r = int(bad[0]) + 1
        raise LogError(f"{path}: row {rows[r]}: time {data[r, 0]:g} does not increase (previous {data[r - 1, 0]:g})")
    data = _check_ranges(path, data, rows, meta.schema)
    if meta.breaks and meta.breaks[-1] >= n:
        raise LogError(f"{path}: its sidecar marks a break at row {meta.breaks[-1]}, but the log has {n} rows")
    ns, nc = len(meta.schema.states), len(meta.schema.channels)
    return Log(
        path,
        data[:, 0].copy(),
        data[:, 1 : 1 + ns].copy(),
        data[:, 1 + ns : 1 + nc].copy(),
        meta,
        data[:, 1 + nc :].copy(),
    )


def _fmt(v: float) -> str:
    return repr(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def write_log(log: Log, path: str | os.PathLike) -> Path:
    """Write ``log`` as CSV plus sidecar, each atomically (sidecar first, then the CSV it describes)."""
    path = Path(path)
    lines = [",".join(log.meta.schema.columns)]
    n_logged = len(log.meta.schema.logged)
    if log.logged is None or log.logged.shape != (len(log), n_logged):
        raise ValueError(
            f"{path}: the log holds {0 if log.logged is None else log.logged.shape[1]} logged "
            f"column(s), its schema declares {n_logged}"
        )
    for t, s, a, extra in zip(log.time, log.states, log.actions, log.logged):
        lines.append(",".join(_fmt(v) for v in (t, *s, *a, *extra)))
    atomic_write_text(sidecar_path(path), json.dumps(log.meta.to_json(), indent=1) + "\n")
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


# ---------------------------------------------------------------- datasets of many logs

_NON_FINITE = re.compile(r"^[+-]?(?:nan|inf|infinity)$", re.IGNORECASE)


def _number(text: str) -> float | int | str:
    """A file-name field as a number when it is one written in ASCII digits (``30``, ``0.5``),
    else the word itself; ``1_0`` and ``\u0661`` stay words, as a human reads them."""
    if _NUMBER.match(text):
        value = float(text)
        if math.isfinite(value):
            return int(text) if re.fullmatch(r"[+-]?[0-9]+", text) else value
    return text


def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


#: two control periods differ when they are more than this fraction apart: a simulated log records its
#: initial log's measured period (40 or 41 ms for a 40 ms loop)
PERIOD_TOLERANCE = 0.1


def off_period(log: Log, period_ms: float) -> float | None:
    """The log's median row interval when it is another period than ``period_ms`` (beyond
    :data:`PERIOD_TOLERANCE`); None when it agrees or the log has too few rows to say."""
    if len(log) < 3:
        return None
    median = float(np.median(np.diff(log.time)))
    return median if abs(median - period_ms) > PERIOD_TOLERANCE * period_ms else None


def _period_agrees(log: Log, system: SystemDescription) -> None:
    """A log without sidecar is taken at the description's period: refuse one whose rows are another
    period apart (median interval off by more than :data:`PERIOD_TOLERANCE`). 80 ms logs beside
    40 ms ones were once split, verified and simulated against a 40 ms model without a word."""
    median = None if system.period_ms is None else off_period(log, system.period_ms)
    if median is not None:
        raise LogError(
            f"{log.path}: its rows are {median:g} ms apart (median), but the system description "
            f"{system.name!r} says a {system.period_ms:g} ms period; give logs of that period or a "
            "description of theirs (--system)"
        )


def _meta_for(path: Path, system: SystemDescription, rx: re.Pattern[str] | None) -> LogMeta | None:
    """The metadata a log without sidecar gets from the system description (None: the file does
    not match the pattern)."""
    fields: dict[str, Any] = {}
    run: Any = path.stem
    if rx is not None:
        m = rx.match(path.name)
        if m is None:
            return None
        fields = {k: _number(v) for k, v in m.groupdict().items()}
        odd = [
            f"{k}={v}"
            for k, v in fields.items()
            if k != "run" and isinstance(v, str) and (_NON_FINITE.match(v) or _NUMBER.match(v))
        ]
        if odd:
            raise LogError(f"{path}: the file name's field {odd[0]} is not a finite number")
        run = fields.pop("run", path.stem)
    spec = system.controller_for(fields)
    if spec is not None and any(p not in fields for p in system.versions.params):
        spec = None  # the file name does not say the version: a default would pass for the log's own (x = 30)
    return LogMeta(
        schema=system.schema,
        controller=None if spec is None else spec.to_json(),
        period_ms=system.period_ms,
        run_id=safe_run_id(run, str(path)),
        source="fot",
        provenance={"file": path.name},
    )


def _agree(log: Log, expected: LogMeta | None, system: SystemDescription | None) -> None:
    """A sidecar must agree with the system description and the file-name pattern: a conflict is an
    error naming both, never a silent override."""
    if system is not None and log.meta.schema.columns != system.schema.columns:
        raise LogError(
            f"{sidecar_path(log.path) if log.path else log.name}: sidecar declares columns "
            f"{','.join(log.meta.schema.columns)}, the system description "
            f"{system.source or system.name} {','.join(system.schema.columns)}"
        )
    if expected is None or expected.controller is None or log.meta.controller is None:
        return
    pattern_params = {
        k: v for k, v in expected.controller["params"].items() if system is not None and k in system.versions.params
    }
    side_params = log.meta.controller.get("params", {})
    for k, v in pattern_params.items():
        if k in side_params and str(side_params[k]) != str(v) and _number(str(side_params[k])) != v:
            raise LogError(f"{log.path}: the file name says {k}={v}, its sidecar says {k}={side_params[k]}")


def list_log_files(folder: Path, pattern: str | None) -> list[Path]:
    """Log files of a folder in a stable, natural order (log_30_2 before log_30_10)."""
    if not folder.is_dir():
        raise LogError(f"{folder}: not a folder")
    rx = pattern_regex(pattern) if pattern else None
    files = [p for p in folder.iterdir() if p.suffix == ".csv" and not p.name.startswith(".")]
    if rx is not None:
        files = [p for p in files if rx.match(p.name)]
    return sorted(files, key=_natural_key)


def folder_logs(folder: str | os.PathLike) -> list[Path]:
    """The files of ``folder`` that are logs to the reader: every CSV :func:`load_logs` of the folder
    would read and every ``.meta.json`` sidecar (of those, or left without its CSV, which a later log
    of that name would inherit). Empty for a missing folder. What a command writing logs refuses to
    mix a new run with, and all its ``--force`` removes: any other file in the folder is the user's."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    sidecars = [p for p in folder.glob("*.meta.json") if not p.name.startswith(".")]
    logs = [p for p in list_log_files(folder, None) if not p.is_dir()]  # a folder named x.csv is no log
    return logs + sorted(sidecars, key=_natural_key)


def refuse_earlier_logs(folder: str | os.PathLike, force: bool, option: str = "--out") -> None:
    """A ValueError naming the folder, how many logs it holds (see :func:`folder_logs`) and ``--force``
    when it holds any and ``force`` is off: new logs written among those of an earlier run would be
    read back as one dataset. Call it before any work."""
    held = folder_logs(folder)
    if held and not force:
        n_csv = sum(p.suffix == ".csv" for p in held)
        what = f"{n_csv} log{'s' * (n_csv != 1)}" if n_csv else f"{len(held)} log sidecar{'s' * (len(held) != 1)}"
        raise ValueError(
            f"{option} {folder}: holds {what} of an earlier run; pass --force to replace them "
            "(other files stay) or choose an empty folder"
        )


def remove_logs(folder: str | os.PathLike) -> int:
    """Delete the log files :func:`folder_logs` finds (nothing else); returns how many CSV logs went."""
    held = folder_logs(folder)
    for p in held:
        p.unlink(missing_ok=True)
    return sum(p.suffix == ".csv" for p in held)


@dataclass
class StagedLogs:
    """Where :func:`staged_logs` has the new logs written, and how many earlier CSV logs they replaced."""

    folder: Path
    replaced: int = 0


@contextlib.contextmanager
def staged_logs(out: str | os.PathLike, force: bool) -> Iterator[StagedLogs]:
    """Write a run's logs into a hidden folder inside ``out``; only when the block ends without error
    are the earlier logs removed (``force``; see :func:`refuse_earlier_logs`) and the new ones moved
    in. A simulation that fails half-way (a controller that raises, Ctrl-C) leaves ``out`` exactly as
    it was: neither the earlier run lost nor half of a new one mixed into it."""
    out = Path(out)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    staged = StagedLogs(Path(tempfile.mkdtemp(dir=out, prefix=".staging-")))
    done = False
    try:
        yield staged
        refuse_earlier_logs(out, force)  # a log that appeared meanwhile is not silently replaced
        staged.replaced = remove_logs(out) if force else 0
        for p in sorted(staged.folder.iterdir()):
            os.replace(p, out / p.name)
        done = True
    finally:
        shutil.rmtree(staged.folder, ignore_errors=True)
        if created and not done:  # a folder this run made and filled with nothing goes too
            with contextlib.suppress(OSError):
                out.rmdir()


def _manifest_error(path: Path, why: str) -> LogError:
    return LogError(f"{path}: not a valid manifest ({why})")


def load_manifest(path: Path) -> tuple[SystemDescription | None, list[Path]]:
    """A manifest is JSON ``{"system": {...}, "logs": [files]}`` as :func:`write_manifest` writes it
    (older ones: ``{"pattern": ..., "schema": ..., "logs": ...}``). Paths are relative to it."""
    if path.name.endswith(".meta.json"):
        raise _manifest_error(path, "it is a log's sidecar: give the log's .csv, its folder, or a manifest")
    d = read_json(path, "manifest")
    if not isinstance(d, dict):
        raise _manifest_error(path, f"a JSON object is needed, not {type(d).__name__}")
    if not {"logs", "system", "schema", "pattern"} & d.keys():  # any other JSON would read the whole folder
        raise _manifest_error(path, "it has none of the keys 'logs', 'system', 'schema', 'pattern'")
    system = None
    try:
        if d.get("system") is not None:
            system = SystemDescription.from_json(d["system"], f"{path}: system")
        elif "schema" in d or "pattern" in d:
            base = describe_schema(LogSchema.from_json(d["schema"])) if "schema" in d else lane_keeping()
            system = base.with_pattern(d.get("pattern"))
    except ValueError as exc:
        raise _manifest_error(path, str(exc)) from None
    logs = d.get("logs")
    if logs is None:
        return system, list_log_files(path.parent, system.versions.pattern if system else None)
    if not isinstance(logs, list) or not all(isinstance(f, str) and f for f in logs):
        raise _manifest_error(path, "'logs' must be a list of file names")
    return system, [path.parent / f for f in logs]


def write_manifest(path: Path, logs: Sequence[Log], system: SystemDescription | None) -> None:
    """The exact set of logs with the description that reads them, so a manifest reads back alone."""
    manifest = {
        "system": None if system is None else system.to_json(),
        "logs": [str(Path(lg.path).resolve()) for lg in logs if lg.path],
    }
    atomic_write_text(path, json.dumps(manifest, indent=1) + "\n")


def load_logs(
    sources: Sequence[str | os.PathLike] | str | os.PathLike,
    system: SystemDescription | None = None,
    min_length: int = 1,
    skip_bad: bool = False,
    where: dict[str, Any] | None = None,
) -> list[Log]:
    """Load logs from files, folders or ``*.json`` manifests; sorted, validated, one schema.

    ``system`` describes logs without sidecar (columns, version parameters from the file name, the
    controller) and is checked against those with one; without it, logs must carry sidecars, except
    that the paper's lane-keeping robot is assumed for a bare ``time,color,angle`` log. ``where``
    keeps only logs whose controller parameters match (e.g. ``{"x": [10, 30, 50]}``). With
    ``skip_bad`` a broken file is reported as a warning and skipped; by default it stops.
    """
    if isinstance(sources, (str, os.PathLike)):
        sources = [sources]
    entries: list[tuple[Path, SystemDescription | None]] = []
    for src in sources:
        p = Path(src)
        if p.suffix == ".json" and p.is_file():
            msys, files = load_manifest(p)
            if system is not None and msys is not None and msys.schema.columns != system.schema.columns:
                raise LogError(
                    f"{p}: the manifest's system ({','.join(msys.schema.columns)}) differs from the "
                    f"one given ({','.join(system.schema.columns)})"
                )
            entries += [(f, msys or system) for f in files]
        elif p.is_dir():
            pattern = system.versions.pattern if system else None
            found = list_log_files(p, pattern)
            if not found:
                raise LogError(f"{p}: a folder holding no logs ({pattern or '*.csv'})")
            entries += [(f, system) for f in found]
        elif p.exists():
            entries.append((p, system))
        else:
            raise LogError(f"{p}: no such file or folder")
    first: dict[Path, tuple[Path, SystemDescription | None]] = {}
    for f, fsys in entries:  # a file named twice (a folder and a file in it) is read once
        try:
            target = f.resolve()
        except (RuntimeError, OSError):  # Python 3.11 says 'Symlink loop' with a RuntimeError
            raise LogError(f"{f}: a symbolic link that loops (it never reaches a file)") from None
        first.setdefault(target, (f, fsys))
    entries = list(first.values())
    logs: list[Log] = []
    skipped: list[str] = []
    for f, fsys in entries:
        try:
            if fsys is None and not sidecar_path(f).exists():
                fsys = lane_keeping()
            rx = pattern_regex(fsys.versions.pattern) if fsys is not None and fsys.versions.pattern else None
            meta = _meta_for(f, fsys, rx) if fsys is not None else None
            if fsys is not None and meta is None:
                raise LogError(f"{f}: the file name does not match the pattern {fsys.versions.pattern!r}")
            log = read_log(f, meta, min_length=min_length, ignore=fsys.ignore if fsys else ())
            if meta is not None and not sidecar_path(f).exists():
                _period_agrees(log, fsys)
            _agree(log, meta, fsys if sidecar_path(f).exists() and fsys is not None and fsys is system else None)
        except (LogError, ValueError) as exc:
            msg = str(exc) if str(f) in str(exc) or str(sidecar_path(f)) in str(exc) else f"{f}: {exc}"
            if not skip_bad:
                raise LogError(msg) from None
            warnings.warn(f"skipping bad log: {msg}", stacklevel=2)
            skipped.append(msg)
            continue
        logs.append(log)
    read_ok = len(logs)
    if where and logs:
        params = [_version_params(lg, system) for lg in logs]
        known = sorted({k for p in params for k in p})
        unknown = [k for k in where if k not in known]
        if unknown:  # not 'no logs found': the user misspelt a parameter, say which and what there is
            raise LogError(
                f"{', '.join(map(str, sources))}: no log has the parameter {unknown[0]!r} "
                f"(their parameters: {', '.join(known) or 'none'}"
                + ("; a --system names the version parameters)" if system is None else ")")
            )
        logs = [lg for lg, p in zip(logs, params) if _matches(p, where)]
    if not logs:
        if not sources:  # 'logs = []' in a run file once said ': no logs found'
            raise LogError("no logs given: name log files, folders or manifests")
        if skipped and not read_ok:  # the one error line says why, since a failed command's warnings are not shown
            raise LogError(f"every log was bad and skipped ({len(skipped)}); the first: {skipped[0]}")
        raise LogError(f"{', '.join(map(str, sources))}: no logs found" + (f" matching {where}" if where else ""))
    first = logs[0]
    for lg in logs[1:]:
        if lg.meta.schema.columns != first.meta.schema.columns:
            raise LogError(
                f"{lg.path}: schema {lg.meta.schema.columns} differs from {first.path}: "
                f"{first.meta.schema.columns} (mixed schemas in one dataset)"
            )
    timed = [lg for lg in logs if lg.meta.period_ms is not None]
    for lg in timed[1:]:
        ref = timed[0]
        # one model, one control period: never mixed
        if abs(lg.meta.period_ms - ref.meta.period_ms) > PERIOD_TOLERANCE * ref.meta.period_ms:
            raise LogError(
                f"{lg.path or lg.name}: recorded at a {lg.meta.period_ms:g} ms period, {ref.path or ref.name} "
                f"at {ref.meta.period_ms:g} ms (mixed control periods in one dataset)"
            )
    return logs


def logs_fit_model(
    logs: Sequence[Log], schema: LogSchema, model: str | os.PathLike, period_ms: float | None = None
) -> list[Log]:
    """The logs, if they hold the states and actions the model was trained on (in its order) and,
    given the model's control period, rows that far apart (median interval within 10 %): a model
    run on another system's logs otherwise fails deep inside with a message naming neither, and a
    40 ms model once simulated from 80 ms logs without a word."""
    want = [c.name for c in schema.states], [c.name for c in schema.actions]
    for lg in logs:
        median = None if period_ms is None else off_period(lg, period_ms)
        if median is not None:
            raise LogError(
                f"{lg.path or lg.name}: its rows are {median:g} ms apart (median), the model {model} "
                f"was trained at a {period_ms:g} ms period"
            )
        have = [c.name for c in lg.meta.schema.states], [c.name for c in lg.meta.schema.actions]
        if have != want:
            raise LogError(
                f"{lg.path or lg.name}: holds states {','.join(have[0])} and actions {','.join(have[1])}, "
                f"the model {model} reads states {','.join(want[0])} and actions {','.join(want[1])} "
                "(a model of another system?)"
            )
    return list(logs)


def _version_params(log: Log, system: SystemDescription | None) -> dict[str, Any]:
    """The parameters ``where`` selects on: the description's version parameters (the car's
    ``kp_steer`` sits in ``loops.0.params.kp``) with the controller's own top-level ones."""
    if system is None or not system.versions.params or not log.meta.controller:
        return log.param
    return {**log.param, **system.version_of(log.controller)}


def _matches(params: dict[str, Any], where: dict[str, Any]) -> bool:
    for k, want in where.items():
        allowed = want if isinstance(want, (list, tuple, set)) else [want]
        have = params.get(k)
        if have not in allowed and str(have) not in {str(a) for a in allowed} and not _same_number(have, allowed):
            return False
    return True


def _same_number(value: Any, allowed: Iterable[Any]) -> bool:
    """Whether ``value`` equals one of ``allowed`` as numbers: '--where x=3e1' selects x = 30."""

    def number(x: Any) -> float | None:
        try:
            return float(x)
        except (TypeError, ValueError, OverflowError):
            return None

    v = number(value)
    return v is not None and any(number(a) == v for a in allowed)


def group_by_param(logs: Iterable[Log], key: str) -> dict[Any, list[Log]]:
    """Logs grouped by one controller parameter, keys sorted."""
    out: dict[Any, list[Log]] = {}
    for lg in logs:
        out.setdefault(lg.param.get(key), []).append(lg)
    return dict(sorted(out.items(), key=lambda kv: (str(type(kv[0])), kv[0])))


def group_by_controller(logs: Iterable[Log]) -> dict[ControllerSpec, list[Log]]:
    """Logs per controller version (name and parameters), in a stable order: a metric distribution
    only means something for one version. Every log must say its controller."""
    out: dict[ControllerSpec, list[Log]] = {}
    for lg in logs:
        out.setdefault(lg.controller, []).append(lg)
    return dict(sorted(out.items(), key=lambda kv: kv[0].key))

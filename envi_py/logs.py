"""Field and simulated logs: one CSV per run plus an optional ``<name>.meta.json`` sidecar.

A log is ``time`` in milliseconds, then the state columns, then the action columns. Real
field-test (FOT) logs, twin logs, hardware-in-the-loop logs and simulated traces are all written
and read through this module, so every downstream tool treats them alike. The reader is strict:
every problem is reported with the file and the row, because a silently mangled log poisons every
model trained on it.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import re
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from .system import Channel, LogSchema, lane_keeping, pattern_regex

__all__ = ["Channel", "LogSchema", "pattern_regex"]

SCHEMA_VERSION = 1
SOURCES = ("fot", "sim", "twin", "hil")


class LogError(ValueError):
    """A log file (or a set of logs) that cannot be used; the message names file and row."""


#: The lane-keeping robot: a reflected-light colour reading (0 = black, 100 = white) and a
#: steering angle in degrees, as its shipped system description declares them.
LANE_KEEPING_SCHEMA = lane_keeping().schema


@dataclass
class LogMeta:
    """What the sidecar records. Everything but the schema is optional for a field log."""

    schema: LogSchema = LANE_KEEPING_SCHEMA
    controller: dict[str, Any] | None = None  # {"name": ..., "params": {...}}
    period_ms: float | None = None
    run_id: str | None = None
    source: str = "fot"
    provenance: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {
            "schema_version": SCHEMA_VERSION,
            **self.schema.to_json(),
            "controller": self.controller,
            "period_ms": self.period_ms,
            "run_id": self.run_id,
            "source": self.source,
            "provenance": self.provenance,
        }

    @staticmethod
    def from_json(d: dict[str, Any], where: str) -> "LogMeta":
        version = d.get("schema_version")
        if version != SCHEMA_VERSION:
            raise LogError(f"{where}: sidecar schema_version {version!r} is not supported (expected {SCHEMA_VERSION})")
        source = d.get("source", "fot")
        if source not in SOURCES:
            raise LogError(f"{where}: sidecar source {source!r} is not one of {', '.join(SOURCES)}")
        try:
            schema = LogSchema.from_json(d)
        except (KeyError, TypeError, ValueError) as exc:
            raise LogError(f"{where}: sidecar has no valid states/actions declaration ({exc})") from exc
        period = d.get("period_ms")
        return LogMeta(schema=schema, controller=d.get("controller"),
                       period_ms=None if period is None else float(period),
                       run_id=d.get("run_id"), source=source, provenance=dict(d.get("provenance") or {}))


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

    def sha256(self) -> str:
        """Hash of the numeric content, so a checkpoint can name exactly what it was trained on."""
        h = hashlib.sha256()
        for arr in (self.time, self.states, self.actions):
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
        return h.hexdigest()


def sidecar_path(csv_path: Path) -> Path:
    return csv_path.with_name(csv_path.stem + ".meta.json")


def _parse_cell(text: str, path: Path, row: int, col: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise LogError(f"{path}: row {row}: column '{col}' has non-numeric value {text!r}") from None
    if not math.isfinite(value):
        raise LogError(f"{path}: row {row}: column '{col}' is {text!r} (NaN/inf are not valid readings)")
    return value


def read_log(path: str | os.PathLike, meta: LogMeta | None = None, min_length: int = 1) -> Log:
    """Read and validate one CSV log.

    ``meta`` describes a log that has no sidecar (e.g. the real lane-keeping logs); a sidecar, when
    present, wins. ``min_length`` is the history window: a shorter log cannot give one training pair.
    Row numbers in errors count the header as row 1, as a spreadsheet shows them.
    """
    path = Path(path)
    side = sidecar_path(path)
    if side.exists():
        try:
            meta = LogMeta.from_json(json.loads(side.read_text()), str(side))
        except json.JSONDecodeError as exc:
            raise LogError(f"{side}: not valid JSON ({exc})") from exc
    meta = meta or LogMeta()
    expected = meta.schema.columns
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise LogError(f"{path}: cannot read ({exc.strerror})") from exc
    except (UnicodeDecodeError, csv.Error) as exc:
        raise LogError(f"{path}: not a text CSV file ({exc})") from exc
    if not rows:
        raise LogError(f"{path}: empty file (expected header {','.join(expected)})")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in expected if c not in header]
    extra = [c for c in header if c not in expected]
    if missing or extra:
        parts = []
        if missing:
            parts.append("missing column(s) " + ", ".join(missing))
        if extra:
            parts.append("unexpected column(s) " + ", ".join(extra))
        raise LogError(f"{path}: row 1: {'; '.join(parts)} (expected {','.join(expected)})")
    order = [header.index(c) for c in expected]
    data = np.empty((len(rows) - 1, len(expected)), dtype=np.float64)
    n = 0
    for i, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue  # a trailing blank line is not a reading
        if len(row) != len(header):
            raise LogError(f"{path}: row {i}: {len(row)} cells, header has {len(header)}")
        data[n] = [_parse_cell(row[j].strip(), path, i, expected[k]) for k, j in enumerate(order)]
        n += 1
    data = data[:n]
    if n < max(min_length, 1):
        raise LogError(f"{path}: {n} data rows, shorter than the {min_length} the history window needs")
    dt = np.diff(data[:, 0])
    bad = np.nonzero(dt <= 0)[0]
    if bad.size:
        r = int(bad[0]) + 3
        raise LogError(f"{path}: row {r}: time {data[r - 2, 0]:g} does not increase (previous {data[r - 3, 0]:g})")
    ns, nc = len(meta.schema.states), len(meta.schema.channels)
    return Log(path, data[:, 0].copy(), data[:, 1:1 + ns].copy(), data[:, 1 + ns:1 + nc].copy(), meta,
               data[:, 1 + nc:].copy())


def _atomic_write(path: Path, text: str) -> None:
    """Write via a temporary file and rename, so a crash never leaves half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w", newline="") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _fmt(v: float) -> str:
    return repr(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(float(v))


def write_log(log: Log, path: str | os.PathLike) -> Path:
    """Write ``log`` as CSV plus sidecar, each atomically (sidecar first, then the CSV it describes)."""
    path = Path(path)
    lines = [",".join(log.meta.schema.columns)]
    n_logged = len(log.meta.schema.logged)
    if log.logged is None or log.logged.shape != (len(log), n_logged):
        raise ValueError(f"{path}: the log holds {0 if log.logged is None else log.logged.shape[1]} logged "
                         f"column(s), its schema declares {n_logged}")
    for t, s, a, extra in zip(log.time, log.states, log.actions, log.logged):
        lines.append(",".join(_fmt(v) for v in (t, *s, *a, *extra)))
    _atomic_write(sidecar_path(path), json.dumps(log.meta.to_json(), indent=1) + "\n")
    _atomic_write(path, "\n".join(lines) + "\n")
    return path


# ---------------------------------------------------------------- datasets of many logs

def _number(text: str) -> float | int | str:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


@dataclass
class DatasetSpec:
    """How to read a folder of logs that may lack sidecars.

    ``pattern`` fields become controller parameters, except ``run`` which becomes the run id;
    ``controller`` names the controller that produced the logs.
    """

    pattern: str | None = None
    controller: str = "lane-keeping"
    schema: LogSchema = LANE_KEEPING_SCHEMA
    period_ms: float | None = None
    source: str = "fot"
    fixed_params: dict[str, Any] = field(default_factory=dict)


def _meta_for(path: Path, spec: DatasetSpec, rx: re.Pattern[str] | None) -> LogMeta | None:
    if rx is None:
        return LogMeta(schema=spec.schema, controller={"name": spec.controller, "params": dict(spec.fixed_params)},
                       period_ms=spec.period_ms, run_id=path.stem, source=spec.source)
    m = rx.match(path.name)
    if m is None:
        return None
    fields = {k: _number(v) for k, v in m.groupdict().items()}
    run = fields.pop("run", path.stem)
    params = {**spec.fixed_params, **fields}
    return LogMeta(schema=spec.schema, controller={"name": spec.controller, "params": params},
                   period_ms=spec.period_ms, run_id=str(run), source=spec.source,
                   provenance={"file": path.name})


def list_log_files(folder: Path, spec: DatasetSpec) -> list[Path]:
    """Log files of a folder in a stable, natural order (log_30_2 before log_30_10)."""
    if not folder.is_dir():
        raise LogError(f"{folder}: not a folder")
    rx = pattern_regex(spec.pattern) if spec.pattern else None
    files = [p for p in folder.iterdir() if p.suffix == ".csv" and not p.name.startswith(".")]
    if rx is not None:
        files = [p for p in files if rx.match(p.name)]
    return sorted(files, key=_natural_key)


def load_manifest(path: Path) -> tuple[DatasetSpec, list[Path]]:
    """A manifest is JSON: {"schema": {...}?, "controller": name, "pattern": ..., "logs": [files]?}."""
    try:
        d = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise LogError(f"{path}: cannot read manifest ({exc})") from exc
    spec = DatasetSpec(pattern=d.get("pattern"), controller=d.get("controller", "lane-keeping"),
                       schema=LogSchema.from_json(d["schema"]) if "schema" in d else LANE_KEEPING_SCHEMA,
                       period_ms=d.get("period_ms"), source=d.get("source", "fot"),
                       fixed_params=dict(d.get("params", {})))
    files = [path.parent / f for f in d["logs"]] if "logs" in d else list_log_files(path.parent, spec)
    return spec, files


def load_logs(sources: Sequence[str | os.PathLike] | str | os.PathLike, spec: DatasetSpec | None = None,
              min_length: int = 1, skip_bad: bool = False,
              where: dict[str, Any] | None = None) -> list[Log]:
    """Load logs from files, folders or a ``*.json`` manifest; sorted, validated, one schema.

    ``where`` keeps only logs whose controller parameters match (e.g. ``{"x": [10, 30, 50]}``).
    With ``skip_bad`` a broken file is reported as a warning and skipped; by default it stops.
    """
    if isinstance(sources, (str, os.PathLike)):
        sources = [sources]
    spec = spec or DatasetSpec()
    entries: list[tuple[Path, DatasetSpec]] = []
    for src in sources:
        p = Path(src)
        if p.suffix == ".json" and p.is_file():
            mspec, files = load_manifest(p)
            entries += [(f, mspec) for f in files]
        elif p.is_dir():
            entries += [(f, spec) for f in list_log_files(p, spec)]
        elif p.is_file():
            entries.append((p, spec))
        else:
            raise LogError(f"{p}: no such file or folder")
    logs: list[Log] = []
    for f, fspec in entries:
        rx = pattern_regex(fspec.pattern) if fspec.pattern else None
        try:
            meta = _meta_for(f, fspec, rx)
            log = read_log(f, meta, min_length=min_length)
        except LogError as exc:
            if not skip_bad:
                raise
            warnings.warn(f"skipping bad log: {exc}", stacklevel=2)
            continue
        logs.append(log)
    if where:
        logs = [lg for lg in logs if _matches(lg, where)]
    if not logs:
        raise LogError(f"{', '.join(map(str, sources))}: no logs found" + (f" matching {where}" if where else ""))
    first = logs[0]
    for lg in logs[1:]:
        if lg.meta.schema.columns != first.meta.schema.columns:
            raise LogError(f"{lg.path}: schema {lg.meta.schema.columns} differs from {first.path}: "
                           f"{first.meta.schema.columns} (mixed schemas in one dataset)")
    return logs


def _matches(log: Log, where: dict[str, Any]) -> bool:
    params = log.param
    for k, want in where.items():
        allowed = want if isinstance(want, (list, tuple, set)) else [want]
        if params.get(k) not in allowed and str(params.get(k)) not in {str(a) for a in allowed}:
            return False
    return True


def group_by_param(logs: Iterable[Log], key: str) -> dict[Any, list[Log]]:
    """Logs grouped by one controller parameter, keys sorted."""
    out: dict[Any, list[Log]] = {}
    for lg in logs:
        out.setdefault(lg.param.get(key), []).append(lg)
    return dict(sorted(out.items(), key=lambda kv: (str(type(kv[0])), kv[0])))

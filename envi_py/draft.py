"""``envi init``: draft a system description from a folder of logs, for the user to edit.

What can be read off the logs is filled in: the columns, each column's observed range (widened to
round numbers, since a valid range is a physical limit, not the data's extent), a resolution where
every value is a multiple of one step, the median period, and a file-name pattern whose numeric
fields become version parameters (the last one the run). What cannot be read off is marked for
the user: which columns are states and which actions (guessed: the first after ``time`` is a
state, the second an action, further ones logged), the controller, and the goals.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from .logs import Log, LogError, LogMeta, read_columns, read_log, read_sidecar, sidecar_path
from .system import Channel, LogSchema, pattern_fields, pattern_regex, toml_value

MAX_FILES = 50


def guess_pattern(names: list[str]) -> str | None:
    """``log_30_0.csv``, ``log_30_1.csv`` ... -> ``log_{v1}_{run}.csv``: digit runs become fields,
    the last one the run id. None when the names do not share one shape."""
    shapes = {re.sub(r"\d+(?:\.\d+)?", "#", n) for n in names}
    if len(shapes) != 1:
        return None
    shape = shapes.pop()
    k = shape.count("#")
    if k == 0:
        return None
    fields = [f"v{i + 1}" for i in range(k - 1)] + ["run"]
    out = shape
    for f in fields:
        out = out.replace("#", "{" + f + "}", 1)
    return out


def _fields_named_by_sidecars(pattern: str, logs: list[Log], paths: list[Path]) -> str:
    """``twin_{v1}_{run}.csv`` -> ``twin_{x}_{run}.csv`` when every sampled log's sidecar gives its
    controller a number ``x`` equal to the file name's ``v1``: the field then says which parameter
    it is, as the description must (a draft's ``v1`` was refused by ``verify``)."""
    rx = pattern_regex(pattern)
    named = {}
    for field in (f for f in pattern_fields(pattern) if f != "run"):
        values = [(rx.match(path.name), lg.meta.controller) for path, lg in zip(paths, logs)]
        if not all(m and c for m, c in values):
            return pattern
        candidates = None
        for m, c in values:
            try:
                value = float(m.group(field))
            except ValueError:  # a field of words ('log_{v1}' of 'log_left'): no number to match
                candidates = set()
                break
            here = {
                k
                for k, v in c.get("params", {}).items()
                if isinstance(v, (int, float)) and not isinstance(v, bool) and value == float(v)
            }
            candidates = here if candidates is None else candidates & here
        if candidates and len(candidates) == 1:
            named[field] = candidates.pop()
    for field, name in named.items():
        pattern = pattern.replace("{" + field + "}", "{" + name + "}")
    return pattern


def _round_out(low: float, high: float) -> tuple[float, float]:
    """A range around the observed one, on round numbers a tenth of the span outside it."""
    span = max(high - low, abs(high), 1e-9)
    if not math.isfinite(span * 1.2):  # values near the float limit: no room to widen
        return low, high
    step = 10 ** math.floor(math.log10(span / 10))
    return math.floor((low - span / 10) / step) * step, math.ceil((high + span / 10) / step) * step


def _resolution(values: np.ndarray) -> float | None:
    """The step every value is a multiple of (1, 0.1, ...), if any of those fits."""
    for step in (1.0, 0.5, 0.1, 0.01):
        if np.allclose(values / step, np.round(values / step), atol=1e-9):
            return step
    return None


def _read_any(path: Path, header: list[str]) -> Log:
    """One log read as strictly as any log (finite numbers, increasing time, a regular UTF-8 file),
    with the first file's columns in its own order and no range yet: the draft is to find them."""
    columns = read_columns(path)
    if sorted(columns) != sorted(header):
        raise LogError(f"{path}: columns {','.join(columns)} differ from {','.join(header)} of the first log")
    if "time" not in columns:
        raise LogError(f"{path}: no 'time' column (milliseconds); envi logs start with it")
    others = [Channel(c) for c in columns if c != "time"]
    if len(others) < 2:
        raise LogError(f"{path}: a log needs at least a state and an action column besides 'time'")
    schema = LogSchema(states=(others[0],), actions=(others[1],), logged=tuple(others[2:]))
    return read_log(path, LogMeta(schema=schema)) if not sidecar_path(path).exists() else _with_sidecar(path, schema)


def _with_sidecar(path: Path, schema: LogSchema) -> Log:
    """A log whose sidecar names its columns: read through the sidecar's schema (the draft takes
    its roles) after checking it names the same columns as the header."""
    log = read_log(path)
    if sorted(log.meta.schema.columns) != sorted(schema.columns):
        raise LogError(
            f"{sidecar_path(path)}: sidecar declares columns {','.join(log.meta.schema.columns)}, the "
            f"file holds {','.join(schema.columns)}"
        )
    return log


def draft_system(folder: Path, pattern: str | None = None) -> str:
    """The TOML text of a draft description of the logs in ``folder``."""
    if not folder.is_dir():
        raise LogError(f"{folder}: not a folder")
    files = sorted(p for p in folder.iterdir() if p.suffix == ".csv" and p.is_file() and not p.name.startswith("."))
    if not files:
        raise LogError(f"{folder}: no .csv logs")
    given = pattern
    pattern = pattern or guess_pattern([p.name for p in files])
    if pattern:
        rx = pattern_regex(pattern)
        unmatched = [p.name for p in files if not rx.match(p.name)]
        if given and unmatched:  # the description would not read these logs back
            raise LogError(
                f"{folder / unmatched[0]}: the file name does not match --pattern {given!r} "
                f"({len(unmatched)} of {len(files)} logs do not)"
            )
    sidecar = next((sidecar_path(p) for p in files if sidecar_path(p).is_file()), None)
    sample = files[:: max(1, len(files) // MAX_FILES)][:MAX_FILES]  # spread over every version
    header = read_columns(sample[0])
    logs = [_read_any(path, header) for path in sample]
    columns = {name: np.concatenate([lg.signal(name) for lg in logs]) for name in header if name != "time"}
    periods = [float(np.median(np.diff(lg.time))) for lg in logs if len(lg) > 1]
    roles = {}
    declared: dict[str, Channel] = {}
    controller = None
    if sidecar is not None:
        meta = read_sidecar(sidecar)
        roles = {
            **{c.name: "state" for c in meta.schema.states},
            **{c.name: "action" for c in meta.schema.actions},
            **{c.name: "logged" for c in meta.schema.logged},
        }
        declared = {c.name: c for c in meta.schema.channels}
        controller = meta.controller
        if pattern and not given:
            pattern = _fields_named_by_sidecars(pattern, logs, sample)
    others = [h for h in header if h != "time"]
    lines = [
        f"# Drafted by 'envi init' from {len(sample)} log(s) of {len(files)} in {folder}.",
        "# Check every line marked CHECK: roles, ranges (physical limits, not the data's extent) and goals.",
        "",
        "[system]",
        f"name = {toml_value(folder.name)}",
    ]
    if periods:
        lines.append(f"period_ms = {toml_value(round(float(np.median(periods)), 3))}")
    for k, name in enumerate(others):
        col = columns[name]
        role = roles.get(name) or ("state" if k == 0 else "action" if k == 1 else "logged")
        guessed = "" if name in roles else "  # CHECK: guessed (state, action, logged or ignore)"
        low, high = _round_out(float(col.min()), float(col.max()))
        side = declared.get(name)
        if side is not None and math.isfinite(side.low) and math.isfinite(side.high):  # declared, not observed
            low, high = side.low, side.high
        lines += [
            "",
            "[[signals]]",
            f"name = {toml_value(name)}",
            f"role = {toml_value(role)}{guessed}",
            f"unit = {toml_value(side.unit)}" if side is not None and side.unit else 'unit = ""  # CHECK',
            f"range = {toml_value([low, high])}  # CHECK: observed {col.min():g}..{col.max():g}",
        ]
        res = _resolution(col)
        if res is not None and role == "state":
            lines.append(f"resolution = {toml_value(res)}")
    lines += ["", "[versions]"]
    if pattern:
        lines.append(f"pattern = {toml_value(pattern)}  # fields become controller parameters, 'run' the run id")
    else:
        lines.append("# no common file-name shape: versions come from sidecars")
    if controller is not None:  # the sidecars' controller; the pattern's fields set its version parameters
        fields = set(pattern_fields(pattern)) if pattern else set()
        params = {k: v for k, v in controller.get("params", {}).items() if k not in fields}
        head = [f"name = {toml_value(controller['name'])}  # from the sidecars", f"params = {toml_value(params)}"]
    else:
        head = [
            'name = "lane-keeping"  # CHECK: a registered controller (bang-bang, pid, combine) '
            "or 'package.module:function'",
            "params = {}",
        ]
    lines += [
        "",
        "[controller]",
        *head,
        "",
        '# [[goals]]  # e.g. metric = "max_abs_dev", signal = "...", setpoint = ...',
        '# [[requirements]]  # e.g. expr = "max_abs_dev(signal, setpoint) <= limit", probability = 0.9',
        "",
    ]
    return "\n".join(lines)

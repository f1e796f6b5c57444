"""Data-quality findings: what is wrong with the logs themselves, reported before any effect.

A pause in the time stamps, a block of rows sent twice, a sensor that stopped updating, a reading
outside the range the system declares, or a session of runs that differs from the others as a
block all show up in the one-step residuals and the goal gaps, where the candidate effects would
explain them as jitter, memory or run-to-run variation. Each check names the file(s), what was
found and how much, in the logs' own units (time stamps in ms, readings in their channel's unit).

The thresholds say what is far outside the rest of the data, not what is physically plausible:

- a *pause* is an interval longer than :data:`PAUSE_FACTOR` times the median interval of all logs;
- a *repeated block* is :data:`REPEAT_ROWS` consecutive rows whose every reading repeats an earlier
  stretch of the same log exactly, or a whole log whose readings equal another's;
- a *frozen* reading is a channel constant for :data:`FROZEN_FACTOR` times the 99th percentile of
  that channel's constant stretches over all logs (and at least :data:`FROZEN_MIN_ROWS` rows);
- *out of range* is outside the declared range of the system description the model was built on;
- a *session* is a consecutive block of one version's logs whose per-log summaries (mean and spread
  of each state) differ from the other blocks' by a Kruskal–Wallis test (scipy.stats.kruskal),
  Holm-corrected over every summary and version. Blocks are the sessions the time stamps show (a
  log starting before the previous one ended starts a new session) when there are at least two of
  :data:`MIN_BLOCK` logs, else :data:`BLOCKS` consecutive blocks of equal size in file order.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..logs import Log, group_by_controller
from ..system import Channel
from .effects import holm

#: An interval this many times the median interval is a pause.
PAUSE_FACTOR = 5.0
#: Rows a repeated block must span (a stretch of a limit cycle rarely repeats exactly for so long).
REPEAT_ROWS = 10
#: A constant stretch this many times the 99th percentile of the channel's stretches is frozen ...
FROZEN_FACTOR = 4.0
#: ... and at least this long.
FROZEN_MIN_ROWS = 10
#: Sessions need this many logs per block; without time-stamp sessions, this many blocks are tested.
MIN_BLOCK, BLOCKS = 3, 4
LEVEL = 0.05


@dataclass(frozen=True)
class QualityFinding:
    """One problem of the logs: its kind, the files it concerns, a sentence and how much."""

    kind: str  # "pause", "repeated", "frozen", "out_of_range", "session"
    files: tuple[str, ...]
    what: str  # what an engineer reads
    amount: float  # how much, in ``unit``
    unit: str
    where: list[dict[str, Any]] = field(default_factory=list)  # per occurrence: file, row, time ...

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "files": list(self.files),
            "what": self.what,
            "amount": self.amount,
            "unit": self.unit,
            "where": self.where,
        }


def _span_text(low: float, high: float) -> str:
    """``10.5`` or ``9.8-14.1``: one pause once read 'jump by 10.5-10.5 s'."""
    return f"{low:.1f}" if f"{low:.1f}" == f"{high:.1f}" else f"{low:.1f}-{high:.1f}"


def _natural(name: str) -> list[Any]:
    """Sort key of a file name with numbers in numeric order (log_30_9 before log_30_10)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _file_row(i: int) -> int:
    """A data row's number in its file as a spreadsheet shows it (the header is row 1)."""
    return i + 2


def pauses(logs: Sequence[Log]) -> list[QualityFinding]:
    """Intervals longer than :data:`PAUSE_FACTOR` times the median interval, with file, time into
    the log and length."""
    dts = [np.diff(lg.time) for lg in logs if len(lg) > 1]
    if not dts:
        return []
    nominal = float(np.median(np.concatenate(dts)))
    where = []
    for lg in logs:
        dt = np.diff(lg.time)
        for i in np.flatnonzero(dt > PAUSE_FACTOR * nominal):
            where.append(
                {
                    "file": lg.name,
                    "row": _file_row(int(i) + 1),
                    "time_s": float((lg.time[i] - lg.time[0]) / 1000.0),
                    "pause_s": float(dt[i] / 1000.0),
                }
            )
    if not where:
        return []
    files = tuple(dict.fromkeys(w["file"] for w in where))
    lengths = [w["pause_s"] for w in where]
    longest = max(where, key=lambda w: w["pause_s"])
    host = next(lg for lg in logs if lg.name == longest["file"])
    span = float((host.time[-1] - host.time[0]) / 1000.0)
    return [
        QualityFinding(
            "pause",
            files,
            f"{len(files)} of {len(logs)} logs pause inside the log: the time stamps jump by "
            f"{_span_text(min(lengths), max(lengths))} s where the median interval is {nominal:.0f} ms "
            f"(longest: {longest['file']} at {longest['time_s']:.1f} s, row {longest['row']}, "
            f"a {longest['pause_s']:.1f} s "
            f"pause in a log spanning {span:.1f} s). The loop did not run meanwhile: the rows on either side "
            "follow each other only if the system stood still (as the real lane robot's do).",
            max(lengths),
            "s",
            where,
        )
    ]


def repeated(logs: Sequence[Log]) -> list[QualityFinding]:
    """Whole logs holding the same readings as another, and stretches of :data:`REPEAT_ROWS` rows
    that repeat an earlier stretch of the same log exactly (not where a state stays constant: that
    is frozen)."""
    out = []
    seen: dict[bytes, str] = {}
    for lg in logs:
        key = np.ascontiguousarray(lg.values).tobytes()
        if key in seen:
            out.append(
                QualityFinding(
                    "repeated",
                    (seen[key], lg.name),
                    f"{lg.name} holds exactly the readings of {seen[key]} ({len(lg)} rows): a copy, not another run.",
                    float(len(lg)),
                    "rows",
                    [{"file": lg.name, "copy_of": seen[key]}],
                )
            )
        else:
            seen[key] = lg.name
    for lg in logs:
        v, n_states = lg.values, lg.states.shape[1]
        first: dict[bytes, int] = {}
        hits = []
        for i in range(len(v) - REPEAT_ROWS + 1):
            block = v[i : i + REPEAT_ROWS]
            if np.any(np.all(block[:, :n_states] == block[0, :n_states], axis=0)):
                continue  # a state constant over the block: frozen, not repeated
            key = np.ascontiguousarray(block).tobytes()
            j = first.setdefault(key, i)
            if j <= i - REPEAT_ROWS:
                hits.append((i, j))
        if hits:
            i, j = hits[0]
            rows = len(hits) + REPEAT_ROWS - 1
            out.append(
                QualityFinding(
                    "repeated",
                    (lg.name,),
                    f"{lg.name}: rows {_file_row(i)}-{_file_row(i + REPEAT_ROWS - 1)} repeat rows "
                    f"{_file_row(j)}-{_file_row(j + REPEAT_ROWS - 1)} reading for reading (about {rows} repeated "
                    "rows in all): a block sent twice by the logger.",
                    float(rows),
                    "rows",
                    [{"file": lg.name, "row": _file_row(i), "repeats_row": _file_row(j)}],
                )
            )
    return out


def _stretches(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start index and length of every stretch of equal consecutive values."""
    change = np.flatnonzero(np.diff(x) != 0) + 1
    starts = np.concatenate([[0], change])
    return starts, np.diff(np.concatenate([starts, [len(x)]]))


def _off_the_limits(x: np.ndarray, starts: np.ndarray, n: np.ndarray, ch: Channel) -> tuple[np.ndarray, np.ndarray]:
    """The stretches (start, length) of ``x`` whose value is not one of the channel's range limits."""
    keep = ~np.isin(x[starts], (ch.low, ch.high))
    return starts[keep], n[keep]


def frozen(logs: Sequence[Log], channels: Sequence[Channel]) -> list[QualityFinding]:
    """Readings (``channels``: the states, first in each log's values) constant for far longer than
    their constant stretches usually last. Commands are the controller's choice, not a sensor's (a
    speed loop at its output limit holds one for a whole run), and a saturating sensor resting at a
    limit reads "nothing in range" (an ultrasonic sensor's 255 cm): neither is a logger that stopped."""
    out = []
    for k, ch in enumerate(channels):
        per = [_stretches(lg.values[:, k]) for lg in logs]
        if ch.saturates:  # stretches at a limit reading are the sensor's answer, not a freeze
            per = [_off_the_limits(lg.values[:, k], st, n, ch) for lg, (st, n) in zip(logs, per)]
        if not any(len(n) for _, n in per):
            continue
        lengths = np.concatenate([n for _, n in per])
        limit = max(FROZEN_MIN_ROWS, FROZEN_FACTOR * float(np.percentile(lengths, 99)))
        where = []
        for lg, (starts, n) in zip(logs, per):
            for s, m in zip(starts, n):
                if m >= limit:
                    where.append(
                        {
                            "file": lg.name,
                            "row": _file_row(int(s)),
                            "rows": int(m),
                            "seconds": float((lg.time[s + m - 1] - lg.time[s]) / 1000.0),
                            "value": float(lg.values[s, k]),
                        }
                    )
        if where:
            worst = max(where, key=lambda w: w["rows"])
            unit = f" {ch.unit}" if ch.unit else ""
            out.append(
                QualityFinding(
                    "frozen",
                    tuple(dict.fromkeys(w["file"] for w in where)),
                    f"{ch.name} stays at one value for {worst['rows']} rows ({worst['seconds']:.1f} s) in "
                    f"{worst['file']} from row {worst['row']} (at {worst['value']:g}{unit}), where 99% of its "
                    f"constant stretches last at most {np.percentile(lengths, 99):.0f} rows: a sensor or logger that "
                    f"stopped updating ({len(where)} such stretch{'es' * (len(where) > 1)}).",
                    float(worst["rows"]),
                    "rows",
                    where,
                )
            )
    return out


def out_of_range(logs: Sequence[Log], channels: Sequence[Channel]) -> list[QualityFinding]:
    """Readings outside the range the system description declares for their channel."""
    out = []
    for k, ch in enumerate(channels):
        where = []
        for lg in logs:
            col = lg.values[:, k]
            bad = np.flatnonzero((col < ch.low) | (col > ch.high))
            if bad.size:
                where.append(
                    {
                        "file": lg.name,
                        "row": _file_row(int(bad[0])),
                        "count": int(bad.size),
                        "value": float(col[bad[0]]),
                    }
                )
        if where:
            n = sum(w["count"] for w in where)
            unit = f" {ch.unit}" if ch.unit else ""
            out.append(
                QualityFinding(
                    "out_of_range",
                    tuple(w["file"] for w in where),
                    f"{n} {ch.name} readings in {len(where)} log{'s' * (len(where) > 1)} lie outside its declared "
                    f"range [{ch.low:g}, {ch.high:g}]{unit} (first: {where[0]['file']} row {where[0]['row']}, "
                    f"{where[0]['value']:g}{unit}).",
                    float(n),
                    "readings",
                    where,
                )
            )
    return out


def _blocks(group: Sequence[Log]) -> tuple[list[list[Log]], str]:
    """Consecutive blocks of one version's logs in file order, and how they were found."""
    order = sorted(group, key=lambda lg: _natural(lg.name))
    sessions: list[list[Log]] = [[order[0]]]
    for prev, lg in zip(order, order[1:]):
        if lg.time[0] < prev.time[-1]:
            sessions.append([])
        sessions[-1].append(lg)
    sessions = [s for s in sessions if len(s) >= MIN_BLOCK]
    if len(sessions) >= 2:
        return sessions, "sessions (the time stamps start again)"
    k = min(BLOCKS, len(order) // MIN_BLOCK)
    if k < 2:
        return [], ""
    return [list(b) for b in np.array_split(np.array(order, dtype=object), k)], "consecutive blocks in file order"


def sessions(logs: Sequence[Log], channels: Sequence[Channel], version_label: Any = None) -> list[QualityFinding]:
    """Logs of one controller version that differ as a block: per log the mean and the standard
    deviation of each state, Kruskal–Wallis over the blocks, Holm over every summary and version."""
    tests = []
    for spec, group in group_by_controller(logs).items():
        blocks, how = _blocks(group)
        if not blocks:
            continue
        label = version_label(spec) if version_label else spec.label()
        for k, ch in enumerate(channels):
            for stat, fn in (("mean", np.mean), ("spread (sd)", np.std)):
                values = [np.array([fn(lg.values[:, k]) for lg in b]) for b in blocks]
                if np.ptp(np.concatenate(values)) == 0:
                    continue
                p = float(stats.kruskal(*values).pvalue)
                tests.append((p, label, ch, stat, blocks, values, how))
    if not tests:
        return []
    adj = holm([t[0] for t in tests])
    out = []
    for (p, label, ch, stat, blocks, values, how), a in zip(tests, adj):
        if a > LEVEL:
            continue
        med = [float(np.median(v)) for v in values]
        pooled = float(np.median(np.concatenate(values)))
        odd = int(np.argmax([abs(m - pooled) for m in med]))
        others = float(np.median(np.concatenate([v for i, v in enumerate(values) if i != odd])))
        names = [lg.name for lg in blocks[odd]]
        unit = f" {ch.unit}" if ch.unit else ""
        out.append(
            QualityFinding(
                "session",
                tuple(names),
                f"{label}: logs {names[0]}..{names[-1]} (block {odd + 1} of {len(blocks)} {how}) differ as a block "
                f"in the {stat} of {ch.name}: median {med[odd]:.3g}{unit} against {others:.3g}{unit} in the other "
                f"blocks (Kruskal-Wallis p={p:.2g}, Holm {a:.2g}; {sum(len(b) for b in blocks)} logs).",
                abs(med[odd] - others),
                ch.unit,
                [{"controller": label, "block": odd + 1, "blocks": len(blocks), "summary": f"{stat} of {ch.name}"}],
            )
        )
    return out


def data_quality(
    logs: Sequence[Log], states: Sequence[Channel], actions: Sequence[Channel], version_label: Any = None
) -> list[QualityFinding]:
    """Every data-quality finding of ``logs`` against the declared ``states`` and ``actions``
    (the model's system description), pauses first."""
    if not logs:
        return []
    channels = list(states) + list(actions)
    return (
        pauses(logs)
        + repeated(logs)
        + frozen(logs, list(states))
        + out_of_range(logs, channels)
        + sessions(logs, list(states), version_label)
    )

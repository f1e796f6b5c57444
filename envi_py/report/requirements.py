"""``envi check``'s report: the verdict per version and requirement first, the intervals as a picture,
the evidence behind each verdict, and the settings with the provenance last."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from .document import Provenance, Report, Section, Text, Table

VERDICT_COLUMNS = [
    "version",
    "requirement",
    "P required",
    "real runs",
    "P (simulation) [interval], runs",
    "P (real system) [interval]",
    "basis",
    "verdict",
    "real runs only [interval]",
]

#: The keys of ``envi check``'s metadata that are provenance proper; the rest are its settings.
_OWN = ("model", "envi", "command", "date", "system")


def verdict_row(r: Any) -> list[str]:
    """One row of the verdict table from a :class:`envi_py.check.CheckRow`."""
    s, q = r.simulation, r.real_system
    p_sim = s["successes"] / s["runs"] if s["runs"] else float("nan")
    return [
        r.version,
        f"{r.requirement}: `{r.expr}`",
        f"{r.p_required:g}",
        str(r.n_real),
        f"{p_sim:.3f} [{s['interval'][0]:.3f}, {s['interval'][1]:.3f}], {s['runs']} ({s['verdict']})",
        f"[{q['interval'][0]:.3f}, {q['interval'][1]:.3f}]",
        str(q["basis"]),
        f"**{q['verdict']}**",
        real_only_text(q),
    ]


def real_only_text(q: dict[str, Any]) -> str:
    """The verdict from the real runs alone (exact Clopper-Pearson), shown beside every combined one so
    a reader sees what the model adds (or that its interval is no narrower); '-' without real runs."""
    r = q.get("real_only")
    if not r or not r.get("n"):
        return "-"
    return f"{r['k']}/{r['n']} [{r['interval'][0]:.3f}, {r['interval'][1]:.3f}] {r['verdict']}"


def method_text(meta: dict[str, Any]) -> str:
    return (
        f"Confidence {1 - meta['alpha']:.0%} (each wrong PASS or FAIL at most {meta['alpha']:.0%}). "
        "Simulation: Wald's SPRT with an indifference region of "
        f"+-{meta['delta']:g} around the required probability, stopped at {meta['max_runs']} runs at most; "
        "its interval is valid at the stopping time. Real system: prediction-powered inference from the "
        "model's predictions and the paired real runs, withdrawn to the real runs alone when the real runs "
        "contradict the model (their count meeting the requirement, their margins, and the mean, spread and "
        "roughness of the signals it reads, each against the runs simulated from the real run's own start); "
        "a version without real runs rests on the model only. Each kept claim "
        "states the smallest error in P(goal) the calibration test catches 80% of the time from its real "
        "runs: a smaller error can pass unseen, and a kept claim of a slightly wrong model may then cover "
        "less than its confidence (measured in benchmarks/coverage_twin.py)."
    )


def evidence_lines(rows: Sequence[Any]) -> list[str]:
    return [
        f"{r.version}, {r.requirement}: {r.real_system.get('reason', '')}. Simulated runs outside the "
        f"training data: {r.outside_training} of {r.sim_runs}." + "".join(f" {n}." for n in r.notes)
        for r in rows
    ]


def provenance_of(meta: dict[str, Any]) -> Provenance:
    """``envi check``'s metadata as provenance: the model (hashed), envi, command and date it
    records; every other key (alpha, seed, ...) is listed as a setting."""
    base = Provenance.collect(meta.get("model"), meta.get("system"))
    return Provenance(
        envi=str(meta.get("envi", base.envi)),
        command=str(meta.get("command", base.command)),
        date=str(meta.get("date", base.date)),
        system=base.system,
        model=base.model,
        model_sha256=base.model_sha256,
        extra={k: v for k, v in meta.items() if k not in _OWN},
    )


def check_report(rows: Sequence[Any], meta: dict[str, Any], figures: bool = True) -> Report:
    """The report of :func:`envi_py.check.check`'s rows; ``meta`` as ``envi check`` writes it."""
    sections = []
    if figures and rows:
        from .plots import requirement_intervals

        sections.append(Section("Intervals", [requirement_intervals(rows)]))
    sections.append(Section("Evidence", [Text(line) for line in evidence_lines(rows)]))
    return Report(
        "Requirement check",
        Table(VERDICT_COLUMNS, [verdict_row(r) for r in rows], numeric=frozenset({2, 3})),
        provenance_of(meta),
        [Text(method_text(meta))],
        sections,
        {**meta, "rows": [r.to_json() for r in rows]},
    )

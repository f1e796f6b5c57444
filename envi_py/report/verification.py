"""``envi verify``'s report: the verdict per version (matched figures beside the real-vs-real floor),
then per-goal tables, trace overlays with fit figures and metric distributions of every version."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .document import Figure, Provenance, Report, Section, Table, Text

GUIDE = (
    "acc: the paper's verification accuracy over the goal metrics (1 = identical means). W1: Wasserstein-1 "
    "between real and simulated goal-metric distributions, divided by the metric's scale. KLD: the authors' "
    "safety/comfort KL divergence (lane keeping only). Floor: the same figure between two halves of the real "
    "runs; sim (matched): a real half against as many simulated runs, so each figure sits beside the floor "
    "resting on equal numbers of runs. A figure near its floor is as close as real runs are to each other. "
    "Test: permutation test of 'simulated runs are exchangeable with real ones' with all real runs against as "
    "many simulated runs. 'n.s.' (p > 0.05) says only that the test could not tell simulated from real runs "
    "with this many real runs, not that they agree: with few runs a large gap can go unseen, so read the "
    "figure beside its floor. 'p<=0.01' is the smallest p the test's permutations can give."
)

TRACE_LOGS = 3  # real logs per version shown in the trace overlay (every log's fit is in the table)


def fmt(v: float | None, spec: str) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)


def test_cell(t: dict[str, Any] | None) -> str:
    if not t:
        return "-"
    smallest = 1.0 / (1 + t.get("permutations", 99))
    p = f"p<={smallest:.2f}" if t["p_value"] <= smallest + 1e-12 else f"p={t['p_value']:.2f}"
    return f"{p} {'n.s.' if t['within_floor'] else 'BEYOND'}"


def verdict_word(r: Any) -> str:
    w = r.within_floor
    if w is None:
        return "no test (fewer than 4 real runs or fewer simulated than real)"
    return "not told apart from real runs (n.s.)" if w else "BEYOND floor"


def summary_row(r: Any) -> list[str]:
    """The verdict table's row of one version (:class:`envi_py.verify.GroupResult`)."""
    fl, mt = r.floor, r.matched
    return [
        r.version,
        str(r.n_real),
        str(r.n_sim),
        str(r.tests.get("per_side", "-")),
        f"{r.sim.acc:.2%}",
        fmt(mt.acc if mt else None, ".2%"),
        fmt(fl.acc if fl else None, ".2%"),
        fmt(mt.w1.mean() if mt else None, ".4f"),
        fmt(fl.w1.mean() if fl else None, ".4f"),
        test_cell(r.tests.get("goals_w1")),
        fmt(mt.kld if mt else None, ".3f"),
        fmt(fl.kld if fl else None, ".3f"),
        test_cell(r.tests.get("kld")),
        verdict_word(r),
    ]


SUMMARY_COLUMNS = [
    "version",
    "real runs",
    "sim runs",
    "runs per side",
    "acc (all runs)",
    "acc sim (matched)",
    "acc floor",
    "mean W1 sim (matched)",
    "mean W1 floor",
    "W1 test",
    "KLD sim (matched)",
    "KLD floor",
    "KLD test",
    "verdict",
]


def goal_table(r: Any) -> Table:
    rows = [
        [
            m,
            f"{r.real_mean[j]:.2f}",
            f"{r.sim_mean[j]:.2f}",
            f"{r.sim.w1[j]:.4f}",
            fmt(r.matched.w1[j] if r.matched else None, ".4f"),
            fmt(r.floor.w1[j] if r.floor else None, ".4f"),
            f"{r.sim.ks[j]:.3f} ({r.sim.ks_p[j]:.2g})",
        ]
        for j, m in enumerate(r.goals)
    ]
    cols = ["goal", "real mean", "sim mean", "W1 (all runs)", "W1 sim (matched)", "W1 floor", "KS (p)"]
    return Table(cols, rows, numeric=frozenset(range(1, 7)))


def _pairs(real: Sequence[Any], sim: Sequence[Any], limit: int | None) -> list[Any]:
    """Real logs with the simulated runs started from their initial windows (matched by the simulated
    log's provenance ``init_log``), cut to a common length."""
    from .plots import TracePair

    by_init: dict[str, list[Any]] = {}
    for s in sim:
        by_init.setdefault(str(s.meta.provenance.get("init_log", "")), []).append(s)
    out = []
    for lg in real:
        runs = by_init.get(lg.name, [])
        if not runs:
            continue
        t = min(len(lg), *(len(s) for s in runs))
        time_s = (lg.time[:t] - lg.time[0]) / 1000.0
        out.append(TracePair(lg.name, time_s, lg.states[:t], np.stack([s.states[:t] for s in runs])))
        if limit is not None and len(out) >= limit:
            break
    return out


def evidence_sections(
    results: Sequence[Any], real: Sequence[Any], sim: Sequence[Any], system: Any, skip: int
) -> list[Section]:
    """Trace overlays with fit figures per version, the fit table, and every version's metric
    distributions (the goal tables of :func:`envi_py.verify.verify`, recomputed per run)."""
    from ..controllers import ControllerSpec
    from ..logs import group_by_controller
    from ..system import describe_schema
    from ..verify import Scoring, _cut
    from .plots import metric_distributions, trace_fits, trace_overlay

    schema = real[0].meta.schema
    system = system or describe_schema(schema)
    channels = [c.name for c in schema.states]
    units = {c.name: c.unit for c in schema.channels}
    period = system.period_ms or float(np.median(np.diff(real[0].time)))
    scoring = Scoring.of(system, schema, skip, period)
    real_g, sim_g = group_by_controller(real), group_by_controller(sim)
    traces: list[Figure] = []
    fit_rows: list[list[str]] = []
    tables_r: dict[str, np.ndarray] = {}
    tables_s: dict[str, np.ndarray] = {}
    for r in results:
        spec = ControllerSpec.from_json(r.controller)
        rl, sl = real_g.get(spec, []), sim_g.get(spec, [])
        if not rl or not sl:
            continue
        pairs = _pairs(rl, sl, None)
        if pairs:
            traces.append(trace_overlay(pairs[:TRACE_LOGS], channels, units, r.version, skip, f"traces_{r.version}"))
            fits = trace_fits(pairs, channels, skip)
            for ch in channels:
                v = np.array([f.fit for f in fits if f.channel == ch])
                v = v[np.isfinite(v)]
                fit_rows.append(
                    [
                        r.version,
                        ch,
                        str(len(v)),
                        str(fits[0].runs),
                        fmt(float(np.median(v)) if len(v) else None, ".1f"),
                        fmt(float(v.min()) if len(v) else None, ".1f"),
                        fmt(float(v.max()) if len(v) else None, ".1f"),
                    ]
                )
        t = min(min(len(lg) for lg in rl), min(len(lg) for lg in sl))
        tables_r[r.version] = scoring.table(scoring.runs([_cut(lg, t) for lg in rl]))
        tables_s[r.version] = scoring.table(scoring.runs([_cut(lg, t) for lg in sl]))
    sections = []
    if traces:
        fit_table = Table(
            ["version", "state", "real logs", "sim runs per log", "median fit %", "min fit %", "max fit %"],
            fit_rows,
            "Fit = 100·(1 − ‖y − ŷ‖/‖y − mean(y)‖) of the simulated trace (the median of the runs from the log's "
            "initial window) to the real one, after the window, as MATLAB's compare: 100 is a perfect match, "
            "0 no better than the real trace's mean, negative worse",
            frozenset(range(2, 7)),
        )
        sections.append(Section("Real vs simulated traces", [fit_table, *traces]))
    if tables_r:
        versions = list(tables_r)
        goal_signals = {g.name: f"{g.signal} [{units.get(g.signal, '')}]".replace(" []", "") for g in scoring.goals}
        sections.append(
            Section(
                "Goal metric distributions",
                [metric_distributions(versions, scoring.names, tables_r, tables_s, goal_signals)],
            )
        )
    return sections


def verification_report(
    results: Sequence[Any],
    title: str = "Verification report",
    extra: dict[str, Any] | None = None,
    real: Sequence[Any] = (),
    sim: Sequence[Any] = (),
    system: Any = None,
    skip: int = 10,
    provenance: Provenance | None = None,
) -> Report:
    """The report of :func:`envi_py.verify.verify`'s results; with the real and simulated logs it
    also holds the trace overlays and metric distributions."""
    sections = [
        Section(
            f"{r.version}",
            [
                Text("Controller: `" + json.dumps(r.controller) + "`"),
                goal_table(r),
                Text("Real logs: " + ", ".join(r.real_logs)),
            ],
        )
        for r in results
    ]
    if real and sim:
        sections = evidence_sections(results, real, sim, system, skip) + sections
    verdict = Table(
        SUMMARY_COLUMNS, [summary_row(r) for r in results], numeric=frozenset({1, 2, 3, 4, 5, 6, 7, 8, 10, 11})
    )
    sys_name = system.name if system is not None else None
    data = {"title": title, **(extra or {}), "groups": [r.to_json() for r in results]}
    return Report(title, verdict, provenance or Provenance.collect(system=sys_name), [Text(GUIDE)], sections, data)

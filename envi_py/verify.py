"""Verification: real runs vs simulated runs of the same controller, goal metric by goal metric.

Runs are grouped by controller version (name and parameters), because a metric distribution only
means something for one version. The goal metrics are the system's (:func:`goals_for`: its preset,
e.g. the paper's eight lane-keeping metrics, and its declared goals; mean, spread and deviation of
every state when it declares none). For each version the report gives, per goal, the real and
simulated means, the Wasserstein-1 distance over the goal's scale and the Kolmogorov-Smirnov
statistic; the paper's accuracy over the goals; for the lane-keeping preset the authors' safety/
comfort KL divergence; and the same figures between real runs (the floor) so a reader sees whether
simulation is already inside real-vs-real variation.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import stats

from .goals.evaluate import Runs, goal_scale, goal_table, signals_of
from .goals.presets import LANE_KEEPING_SIGNAL, goals_of, lane_keeping_centre
from .goals.selection import default_goals
from .controllers import ControllerSpec
from .logs import Log, group_by_controller
from .metrics import Distances, gaussian_kld
from .verdicts import fair_floor, kld_gaussian
from .system import GoalSpec, LogSchema, SystemDescription, describe_schema


def goals_for(system: SystemDescription, schema: LogSchema) -> tuple[GoalSpec, ...]:
    """The goals a simulation can be scored on: the system's goals over simulated signals (states
    and actions), or default ones on every state when it declares none."""
    simulated = {c.name for c in schema.channels}
    goals = tuple(g for g in goals_of(system) if g.signal in simulated)
    if goals:
        return goals
    observed = {c.name: (c.low, c.high) for c in schema.states if math.isfinite(c.low) and math.isfinite(c.high)}
    return default_goals(LogSchema(schema.states, schema.actions), observed)


@dataclass(frozen=True)
class Scoring:
    """How runs are scored: the goals, their scales, the rows skipped (sigma_0) and the period."""

    goals: tuple[GoalSpec, ...]
    schema: LogSchema
    skip: int
    period_ms: float
    pair: bool  # the lane-keeping safety/comfort pair and its KLD apply

    @staticmethod
    def of(system: SystemDescription | None, schema: LogSchema, skip: int, period_ms: float) -> "Scoring":
        system = system or describe_schema(schema)
        return Scoring(
            goals_for(system, schema),
            LogSchema(schema.states, schema.actions),
            skip,
            period_ms,
            system.preset == "lane-keeping" and LANE_KEEPING_SIGNAL in schema.columns,
        )

    @property
    def names(self) -> list[str]:
        return [g.name for g in self.goals]

    def runs(self, logs: Sequence[Log]) -> Runs:
        """The logs' signals (real logs may carry logged-only columns, simulated ones do not)."""
        return signals_of(logs, logs[0].meta.schema, self.skip, self.period_ms)

    def table(self, runs: Runs) -> np.ndarray:
        """(R, G): every goal metric of every run."""
        values = goal_table(self.goals, runs)
        return np.stack([values[g.name] for g in self.goals], axis=1)

    def scales(self, runs: Runs) -> np.ndarray:
        """Each goal's scale (its possible range over these runs), 1 where none is defined. A signal
        declared without a finite range is scaled by the range these runs show: an infinite one once
        fell back to 1 and reported an accuracy of -7929 %."""
        out = []
        channels = {c.name: c for c in self.schema.channels}
        for g in self.goals:
            ch = channels[g.signal]
            low, high = ch.low, ch.high
            if not (math.isfinite(low) and math.isfinite(high)):
                seen = runs.scored(g.signal)
                low, high = float(np.min(seen)), float(np.max(seen))
            s = goal_scale(g, low, high, runs.scored_length, runs.period_ms)
            out.append(s if s is not None and s > 0 and math.isfinite(s) else 1.0)
        return np.array(out)

    def pair_of(self, runs: Runs, centre: float) -> np.ndarray | None:
        """The authors' (safety, comfort) per run: max |c - centre| and max |third difference of c|."""
        if not self.pair:
            return None
        c = runs.scored(LANE_KEEPING_SIGNAL)
        d3 = np.diff(c, n=3, axis=1)
        comfort = np.abs(d3).max(axis=1) if d3.shape[1] else np.zeros(c.shape[0])
        return np.stack([np.abs(c - centre).max(axis=1), comfort], axis=1)


def table_distances(
    mr: np.ndarray, ms: np.ndarray, scale: np.ndarray, pr: np.ndarray | None, ps: np.ndarray | None
) -> Distances:
    """Distances between two samples of runs given their goal tables (R, G) and pairs."""
    w1 = np.array([stats.wasserstein_distance(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]) / scale
    with warnings.catch_warnings():  # with ties scipy falls back from the exact to the asymptotic p-value
        warnings.simplefilter("ignore", RuntimeWarning)
        ks = [stats.ks_2samp(mr[:, j], ms[:, j]) for j in range(mr.shape[1])]
    acc = float(1.0 - np.mean(np.abs(mr.mean(axis=0) - ms.mean(axis=0)) / scale))
    kld = gaussian_kld(pr, ps) if pr is not None and ps is not None else float("nan")
    return Distances(w1, np.array([k.statistic for k in ks]), np.array([k.pvalue for k in ks]), acc, kld)


def split_average(parts: Sequence[Distances]) -> Distances:
    """The distances averaged over random splits; the KLD by its geometric mean, as the authors' analysis
    and benchmarks/fidelity_real.py do: one split whose 2-D Gaussian fit is nearly singular gives a KLD
    in the hundreds, and an arithmetic mean of ten splits then reports that one split."""
    kld = np.array([d.kld for d in parts], dtype=np.float64)
    return Distances(
        np.mean([d.w1 for d in parts], axis=0),
        np.mean([d.ks for d in parts], axis=0),
        np.median([d.ks_p for d in parts], axis=0),
        float(np.mean([d.acc for d in parts])),
        float(np.exp(np.mean(np.log(np.maximum(kld, 1e-12))))) if kld.size else math.nan,
    )


#: Runs per side below which the safety/comfort KLD is not reported: a 2-D Gaussian fit of fewer
#: runs is all ridge (two sets of 2 runs give KLDs in the tens of thousands).
MIN_KLD_SIDE = 5


def fair_reference(
    mr: np.ndarray,
    ms: np.ndarray,
    scale: np.ndarray,
    pr: np.ndarray | None,
    ps: np.ndarray | None,
    seed: int,
    repetitions: int = 10,
    permutations: int = 99,
) -> tuple[Distances, Distances, dict[str, Any]]:
    """The fair real-vs-real reference, at matched sizes (the design of :func:`envi_py.verdicts.fair_floor`,
    one definition everywhere): over ``repetitions`` random splits, every distance between two halves
    of the real runs (the floor) and between the first half and as many simulated runs (matched),
    m = n_real // 2 runs per side; and the permutation tests of "simulated runs are exchangeable with
    real ones" with all real runs against as many simulated runs, on the mean normalised W1 over the
    goals and, for the lane-keeping preset, on the safety/comfort KLD."""
    rng = np.random.default_rng(seed)
    n, m = mr.shape[0], mr.shape[0] // 2
    if m < MIN_KLD_SIDE:  # a 2-D Gaussian fit of fewer runs is degenerate: no KLD figures at all
        pr = ps = None
    floors, matched = [], []
    for _ in range(repetitions):
        order, pick = rng.permutation(n), rng.choice(ms.shape[0], m, replace=False)
        a, b = order[:m], order[m : 2 * m]
        floors.append(
            table_distances(mr[a], mr[b], scale, None if pr is None else pr[a], None if pr is None else pr[b])
        )
        matched.append(
            table_distances(mr[a], ms[pick], scale, None if pr is None else pr[a], None if ps is None else ps[pick])
        )

    def mean_w1(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.mean([stats.wasserstein_distance(x[:, k], y[:, k]) / scale[k] for k in range(x.shape[1])]))

    tests: dict[str, Any] = {
        "per_side": m,
        "goals_w1": fair_floor(mr, ms, mean_w1, repetitions, permutations, seed=seed).to_json(),
    }
    if pr is not None and ps is not None and m >= MIN_KLD_SIDE:
        tests["kld"] = fair_floor(pr, ps, kld_gaussian, repetitions, permutations, seed=seed).to_json()
    return split_average(floors), split_average(matched), tests


def _num(v: float) -> float | None:
    """A number for JSON: NaN (a figure that does not apply) becomes null, so reports are strict JSON."""
    return None if math.isnan(v) else float(v)


def _dist_json(d: Distances, names: Sequence[str]) -> dict[str, Any]:
    return {
        "acc": _num(d.acc),
        "kld": _num(d.kld),
        "w1": {k: _num(v) for k, v in zip(names, d.w1.tolist())},
        "ks": {k: _num(v) for k, v in zip(names, d.ks.tolist())},
        "ks_p": {k: _num(v) for k, v in zip(names, d.ks_p.tolist())},
    }


@dataclass
class GroupResult:
    """Verification of one controller version."""

    controller: dict[str, Any]
    version: str  # the version parameters (``x=30``), or the controller's label
    goals: list[str]
    n_real: int
    n_sim: int
    real_mean: np.ndarray
    sim_mean: np.ndarray
    sim: Distances  # all simulated runs against all real runs
    floor: Distances | None  # real half vs real half (m = n_real // 2 runs per side)
    matched: Distances | None = None  # real half vs m simulated runs: the like-for-like figure to the floor
    tests: dict[str, Any] = field(default_factory=dict)  # permutation tests at n_real runs per side
    real_logs: list[str] = field(default_factory=list)

    @property
    def within_floor(self) -> bool | None:
        """Simulated runs indistinguishable from real ones at equal sizes on every test (None: no test)."""
        tested = [t for k, t in self.tests.items() if isinstance(t, dict)]
        return all(t["within_floor"] for t in tested) if tested else None

    def to_json(self) -> dict[str, Any]:
        return {
            "controller": self.controller,
            "version": self.version,
            "goals": self.goals,
            "n_real": self.n_real,
            "n_sim": self.n_sim,
            "real_mean": dict(zip(self.goals, self.real_mean.tolist())),
            "sim_mean": dict(zip(self.goals, self.sim_mean.tolist())),
            "sim_vs_real": _dist_json(self.sim, self.goals),
            "floor": None if self.floor is None else _dist_json(self.floor, self.goals),
            "matched": None if self.matched is None else _dist_json(self.matched, self.goals),
            "tests": self.tests,
            "within_floor": self.within_floor,
            "real_logs": self.real_logs,
        }


def verify(
    real: Sequence[Log],
    sim: Sequence[Log],
    system: SystemDescription | None = None,
    skip: int = 10,
    floor: bool = True,
    seed: int = 0,
    period_ms: float | None = None,
) -> list[GroupResult]:
    """Compare real and simulated logs per controller version. A version with no simulated runs is
    an error. ``skip`` rows (sigma_0, copied from the real log) are not scored. With ``floor`` (and
    at least 4 real runs) the fair real-vs-real reference is computed (:func:`fair_reference`)."""
    if not real or not sim:
        raise ValueError("verification needs real and simulated logs")
    if skip < 0:
        raise ValueError(f"--skip must be at least 0, got {skip}")
    schema = real[0].meta.schema
    modelled = [c.name for c in schema.states + schema.actions]  # simulated logs carry no logged-only columns
    got = [c.name for c in sim[0].meta.schema.states + sim[0].meta.schema.actions]
    if got != modelled:  # once 'no simulated runs for controller ...'
        raise ValueError(
            f"{sim[0].path or sim[0].name}: signals {','.join(got)} differ from the real logs' "
            f"({real[0].path or real[0].name}: {','.join(modelled)}): simulated from another system?"
        )
    period = (
        period_ms
        or (system.period_ms if system and system.period_ms else None)
        or float(np.median(np.diff(real[0].time)))
    )
    scoring = Scoring.of(system, schema, skip, period)
    centre = lane_keeping_centre(system or describe_schema(schema))
    real_g, sim_g = group_by_controller(real), group_by_controller(sim)
    results = []
    for spec, rl in real_g.items():
        if spec not in sim_g:
            raise ValueError(
                f"{rl[0].path or rl[0].name}: no simulated runs for its controller {spec.label()}; simulated: "
                f"{', '.join(s.label() for s in sim_g) or 'none'}"
            )
        sl = sim_g[spec]
        shortest = min([*rl, *sl], key=len)
        t = len(shortest)
        if t <= skip:  # the scored part of every run is cut to the shortest one's
            raise ValueError(
                f"{shortest.path or shortest.name}: {t} rows; skipping {skip} (--skip) leaves nothing to score"
            )
        rr = scoring.runs([_cut(lg, t) for lg in rl])
        sr = scoring.runs([_cut(lg, t) for lg in sl])
        mr, ms, scale = scoring.table(rr), scoring.table(sr), scoring.scales(rr)
        pr, ps = scoring.pair_of(rr, centre), scoring.pair_of(sr, centre)
        fl = matched = None
        tests: dict[str, Any] = {}
        if floor and len(rl) >= 4 and len(sl) >= len(rl):
            fl, matched, tests = fair_reference(mr, ms, scale, pr, ps, seed)
        results.append(
            GroupResult(
                spec.to_json(),
                version_label(spec, system or describe_schema(schema)),
                scoring.names,
                len(rl),
                len(sl),
                mr.mean(axis=0),
                ms.mean(axis=0),
                table_distances(mr, ms, scale, pr, ps),
                fl,
                matched,
                tests,
                [lg.name for lg in rl],
            )
        )
    return results


def _cut(log: Log, t: int) -> Log:
    """The first ``t`` rows of a log (real and simulated runs are scored over the same span)."""
    if len(log) == t:
        return log
    return Log(log.path, log.time[:t], log.states[:t], log.actions[:t], log.meta, log.logged[:t])


def traces(logs: Sequence[Log], channel: int = 0) -> np.ndarray:
    """One state channel of equally long logs as (R, T); longer logs are cut to the shortest."""
    t = min(len(lg) for lg in logs)
    return np.stack([lg.states[:t, channel] for lg in logs])


def version_label(spec: ControllerSpec, system: SystemDescription) -> str:
    """The version's label (:meth:`SystemDescription.version_label`, the one definition)."""
    return system.version_label(spec)


def to_markdown(results: Sequence[GroupResult], title: str = "Verification report") -> str:
    """Tables a person reads (:mod:`envi_py.report.verification`): the verdict per version with every
    matched figure beside its real-vs-real floor, then per goal; provenance last."""
    from .report.markdown import to_markdown as render
    from .report.verification import verification_report

    return render(verification_report(results, title))


def to_text(results: Sequence[GroupResult]) -> str:
    """A compact screen table: each matched figure beside its real-vs-real floor (accuracy too, so a
    high accuracy and a large KLD can be read against what real runs give), and the tests' verdicts."""
    from .report.verification import fmt, test_cell

    rows = [
        f"{'version':<28} {'real':>5} {'sim':>5} {'acc':>7} {'acc flr':>7} {'W1 sim':>8} {'W1 floor':>8} "
        f"{'W1 test':>14} {'KLD sim':>8} {'KLD floor':>9} {'KLD test':>14}"
    ]
    for r in results:
        fl, mt = r.floor, r.matched
        rows.append(
            f"{r.version[:28]:<28} {r.n_real:>5} {r.n_sim:>5} {fmt(mt.acc if mt else r.sim.acc, '.2%'):>7} "
            f"{fmt(fl.acc if fl else None, '.2%'):>7} "
            f"{fmt(mt.w1.mean() if mt else None, '.4f'):>8} {fmt(fl.w1.mean() if fl else None, '.4f'):>8} "
            f"{test_cell(r.tests.get('goals_w1')):>14} {fmt(mt.kld if mt else None, '.3f'):>8} "
            f"{fmt(fl.kld if fl else None, '.3f'):>9} {test_cell(r.tests.get('kld')):>14}"
        )
    rows.append(
        "acc, W1, KLD: simulated runs against a real half at matched sizes (acc over all runs when there is no "
        "floor); flr/floor: the same between two real halves."
    )
    return "\n".join(rows)


def write_report(
    results: Sequence[GroupResult],
    out: Path,
    title: str = "Verification report",
    extra: dict[str, Any] | None = None,
    real: Sequence[Log] = (),
    sim: Sequence[Log] = (),
    system: SystemDescription | None = None,
    skip: int = 10,
    model: Path | None = None,
) -> tuple[Path, Path]:
    """``report.md``, ``report.html`` and ``report.json`` in ``out`` (and ``report_figures/``). With
    the real and simulated logs the report also shows trace overlays with fit figures and every
    version's metric distributions; ``model``: the checkpoint the simulations came from, named and
    hashed in the provenance. Returns the Markdown and JSON paths."""
    from .report.document import Provenance
    from .report.files import write_files
    from .report.verification import verification_report

    provenance = Provenance.collect(model=model, system=system.name if system is not None else None)
    report = verification_report(results, title, extra, real, sim, system, skip, provenance=provenance)
    files = write_files(report, out, "report")
    return files.markdown, files.json

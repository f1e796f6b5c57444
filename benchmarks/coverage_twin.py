"""Verdicts about the real system, checked where the truth is known: the car twin (issue 15).

Usage: ``python benchmarks/coverage_twin.py [--reps 200] [--real 10] [--quick] [--out bench_out/coverage_twin.json]``.

The car twin plays the real system. Its true P(requirement) per version comes from ``--truth``
(10,000) runs. A *model* is the twin with its own physics, started from the real state at sigma_0
(the real world runs the 3 s warm-up, then the model takes over with fresh noise): what simulating
from a real run's initial window does, with a model whose error is known and set on purpose.

- faithful: the real physics (its only difference is the future noise);
- slightly wrong: motor lag 0.20 s (real 0.15) and colour noise 2.0 (real 1.5);
- badly wrong: motor lag 0.45 s, steering servo 0.15 s (real 0.06), distance noise 3 cm (real 0.7).

Each repetition draws ``--real`` (10) real runs; each real run's own start gets ``--paired`` (40)
model runs (its paired prediction f(s_i)); ``--starts`` (200) further real starts get one model run
each (the unpaired predictions, as the recorded training starts in ``envi check``). Then
:func:`envi_py.verdicts.ppi_verdict` gives the interval for the real P at 95 %, or withdraws the claim
when its validity check rejects: the outcome count against the paired predictions, and each real run's
margin against its own 40 paired margins (``--no-margins``: the outcome count alone), and the
mean, spread and roughness of the signal the requirement reads, by the same test (``--no-summaries``:
without them).
Reported per (model, version, requirement), over ``--reps`` (200)
repetitions: coverage of the truth when the claim is kept, how often it is withdrawn, coverage of
the interval actually reported (kept or the real-only fallback), and the width against the exact
real-only (Clopper-Pearson) interval of the same 10 runs (median ratio).

Then the runs the sequential test in simulation uses (``envi check``'s SPRT) for each version's true
P, at batches of 10 (the default) and 100, against the fixed-size test with the same error rates.

Targets (issue 15): coverage >= 93 % whenever the claim is kept; withdrawn when the model is badly
wrong; width <= 0.6x real-only with a faithful model; the sequential test at most 1/3 of the runs.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envi_py.controllers import ControllerSpec
from envi_py.twin.car import car_versions
from envi_py.twin.car_world import CarBatch, CarProfile
from envi_py.verdicts import fixed_sample_size, ppi_verdict, sprt, trace_summaries

REAL = CarProfile()
MODELS: dict[str, CarProfile] = {
    "faithful": REAL,
    "slightly wrong": replace(REAL, motor_tau_s=0.20, color_noise=2.0),
    "badly wrong": replace(REAL, motor_tau_s=0.45, steer_tau_s=0.15, distance_noise=3.0),
}
VERSIONS = (0, 2)  # kp (0.8, 18) and (1.4, 50): a loose and a tight follower
STEPS, SKIP = 100, 10  # logged rows, and rows of sigma_0 not scored
#: requirement -> its margin per run (>= 0: met), in the metric's unit, as ``MetricRequirement.margin``
MARGINS = {
    "keeps the lane: max|color - 40| <= 10": lambda s: 10 - np.abs(s[:, SKIP:, 0] - 40).max(axis=1),
    "keeps its distance: min(distance) >= 22": lambda s: s[:, SKIP:, 1].min(axis=1) - 22,
}
#: requirement -> the state channel it reads, whose run summaries the validity check also compares
READS = {name: 0 if name.startswith("keeps the lane") else 1 for name in MARGINS}
P_REQUIRED = 0.8


def real_starts(spec: ControllerSpec, n: int, rng: np.random.Generator) -> CarBatch:
    """``n`` real worlds after the warm-up under the controller: the states at sigma_0."""
    world = CarBatch(REAL, n, rng)
    ctrl = spec.build(2, 2, REAL.period_ms)
    ctrl.reset(n)
    for _ in range(REAL.warmup):
        world.apply(ctrl(world.read()))
    return world


def continue_as(world: CarBatch, profile: CarProfile, copies: int, rng: np.random.Generator) -> CarBatch:
    """Each run of ``world`` ``copies`` times, from its current state, under ``profile``'s physics and
    fresh noise (per-run draws such as the lead's cruise speed stay the real ones)."""
    out = copy.copy(world)
    for k, v in vars(world).items():
        if isinstance(v, np.ndarray) and v.shape[:1] == (world.n,):
            setattr(out, k, np.repeat(v, copies, axis=0))
    out.n, out.rng, out.p = world.n * copies, rng, profile
    return out


def logged(world: CarBatch, spec: ControllerSpec) -> np.ndarray:
    """The logged states (runs, STEPS, 2), the controller fresh at row 0 as the twin's logs."""
    ctrl = spec.build(2, 2, world.p.period_ms)
    ctrl.reset(world.n)
    states = np.empty((world.n, STEPS, 2))
    for t in range(STEPS):
        s = world.read()
        states[:, t] = s
        world.apply(ctrl(s))
    return states


def truth(spec: ControllerSpec, runs: int, seed: int) -> dict[str, float]:
    s = logged(real_starts(spec, runs, np.random.default_rng(seed)), spec)
    return {name: float((margin(s) >= 0).mean()) for name, margin in MARGINS.items()}


def repetition(spec: ControllerSpec, model: CarProfile, args: argparse.Namespace, seed: int) -> dict[str, Any]:
    """One whole procedure: 10 real runs, their paired predictions, the unpaired ones, the verdicts."""
    rng = np.random.default_rng(seed)
    start = real_starts(spec, args.real, rng)
    real = logged(continue_as(start, REAL, 1, np.random.default_rng(rng.integers(2**63))), spec)
    paired = logged(continue_as(start, model, args.paired, np.random.default_rng(rng.integers(2**63))), spec)
    other = real_starts(spec, args.starts, rng)
    unpaired = logged(continue_as(other, model, 1, np.random.default_rng(rng.integers(2**63))), spec)
    out = {}
    for name, margin in MARGINS.items():
        real_m, paired_m = margin(real), margin(paired).reshape(args.real, args.paired)
        y = (real_m >= 0).astype(float)
        f = (paired_m >= 0).mean(axis=1)
        margins = {"real_margins": real_m, "paired_margins": paired_m} if args.margins else {}
        if args.summaries:
            mine, theirs = trace_summaries(real[:, SKIP:, READS[name]]), trace_summaries(paired[:, SKIP:, READS[name]])
            margins["summaries"] = {k: (v, theirs[k].reshape(args.real, args.paired)) for k, v in mine.items()}
        v = ppi_verdict(
            (margin(unpaired) >= 0).astype(float), y, f, P_REQUIRED, sims_per_start=args.paired, seed=seed, **margins
        )
        out[name] = {
            "kept": not v.withdrawn,
            "low": v.low,
            "high": v.high,
            "model_low": v.model_estimate.low,
            "model_high": v.model_estimate.high,
            "real_low": v.real_only.low,
            "real_high": v.real_only.high,
        }
    return out


def share_interval(hits: list[bool]) -> list[float] | None:
    """The exact (Clopper-Pearson) 95 % interval of a share: a coverage from 24 kept claims says little."""
    if not hits:
        return None
    ci = stats.binomtest(int(sum(hits)), len(hits)).proportion_ci(0.95, method="exact")
    return [float(ci.low), float(ci.high)]


def summarise(reps: list[dict[str, Any]], p_true: float) -> dict[str, Any]:
    kept = [r for r in reps if r["kept"]]
    cover = [r["low"] <= p_true <= r["high"] for r in reps]
    cover_kept = [r["low"] <= p_true <= r["high"] for r in kept]
    width = [(r["model_high"] - r["model_low"]) / (r["real_high"] - r["real_low"]) for r in kept]
    return {
        "truth": p_true,
        "repetitions": len(reps),
        "kept": len(kept),
        "withdrawn_share": 1 - len(kept) / len(reps),
        "coverage_when_kept": float(np.mean(cover_kept)) if kept else None,
        "coverage_when_kept_ci95": share_interval(cover_kept),
        "coverage_reported": float(np.mean(cover)),
        "width_vs_real_only_median": float(np.median(width)) if width else None,
        "width_vs_real_only_quartiles": [float(q) for q in np.quantile(width, [0.25, 0.75])] if width else None,
        "model_only_coverage": float(np.mean([r["model_low"] <= p_true <= r["model_high"] for r in reps])),
    }


def sequential(p_true: float, reps: int, seed: int) -> dict[str, Any]:
    """Runs the SPRT of ``envi check`` (delta 0.05, alpha = beta = 0.05) uses on a faithful model's
    outcomes, Bernoulli(p_true), at the default batch of 10 and at 100, against the fixed-size test."""
    n_fixed, _ = fixed_sample_size(P_REQUIRED, 0.05, 0.05, 0.05)
    out: dict[str, Any] = {"fixed_n": n_fixed}
    rng = np.random.default_rng(seed)
    for batch in (10, 100):
        runs = [sprt(lambda n: rng.random(n) < p_true, P_REQUIRED, 0.05, batch=batch).runs for _ in range(reps)]
        out[f"batch_{batch}"] = {"median_runs": float(np.median(runs)), "vs_fixed": float(np.median(runs)) / n_fixed}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--real", type=int, default=10, help="real runs per repetition")
    ap.add_argument("--paired", type=int, default=40, help="model runs from each real run's start")
    ap.add_argument("--starts", type=int, default=200, help="further starts, one model run each")
    ap.add_argument("--truth", type=int, default=10_000, help="real runs behind the true probability")
    ap.add_argument("--quick", action="store_true", help="20 repetitions, 2,000 truth runs")
    ap.add_argument(
        "--no-margins",
        dest="margins",
        action="store_false",
        help="validity check on the 0/1 outcomes only (without the margins' PIT test), as before",
    )
    ap.add_argument(
        "--no-summaries",
        dest="summaries",
        action="store_false",
        help="validity check without the run summaries' PIT tests (mean, spread, roughness), as before",
    )
    ap.add_argument(
        "--models", default=",".join(MODELS), help=f"comma-separated models to run (of {', '.join(MODELS)})"
    )
    ap.add_argument("--versions", default=",".join(map(str, VERSIONS)), help="comma-separated car versions")
    ap.add_argument("--out", type=Path, default=Path("bench_out/coverage_twin.json"))
    args = ap.parse_args()
    models = [m.strip() for m in args.models.split(",")]
    unknown = [m for m in models if m not in MODELS]
    if unknown:
        ap.error(f"unknown model(s) {', '.join(unknown)}; known: {', '.join(MODELS)}")
    versions = [int(v) for v in args.versions.split(",")]
    if args.quick:
        args.reps, args.truth = 20, 2000
    specs = car_versions()
    rows, seq, t0 = [], [], time.perf_counter()
    for v in versions:
        spec = specs[v]
        label = (
            f"kp_steer={spec.params['loops'][0]['params']['kp']:g},kp_speed={spec.params['loops'][1]['params']['kp']:g}"
        )
        p_true = truth(spec, args.truth, 10_000 + v)
        for name in MARGINS:
            seq.append(
                {"version": label, "requirement": name, "truth": p_true[name], **sequential(p_true[name], 300, v)}
            )
        for model_name in models:
            model = MODELS[model_name]
            reps = [repetition(spec, model, args, 1000 * v + k) for k in range(args.reps)]
            for name in MARGINS:
                s = summarise([r[name] for r in reps], p_true[name])
                rows.append({"version": label, "model": model_name, "requirement": name, **s})
    print(
        f"P(requirement) of the real system (car twin), 95 % intervals, {args.real} real runs per repetition, "
        f"{args.paired} model runs per real start, {args.starts} further starts; truth from {args.truth} runs"
    )
    print(
        f"{'version':<24} {'model':<15} {'requirement':<40} {'truth':>6} {'kept':>5} {'cov|kept':>9} "
        f"{'[95 %]':>13} {'withdrawn':>9} {'cov rep.':>8} {'width':>6}"
    )
    for r in rows:
        ck = "-" if r["coverage_when_kept"] is None else f"{r['coverage_when_kept']:.1%}"
        ci = r["coverage_when_kept_ci95"]
        ci_text = "-" if ci is None else f"[{ci[0]:.0%}, {ci[1]:.0%}]"
        w = "-" if r["width_vs_real_only_median"] is None else f"{r['width_vs_real_only_median']:.2f}"
        print(
            f"{r['version']:<24} {r['model']:<15} {r['requirement']:<40} {r['truth']:>6.3f} {r['kept']:>5} {ck:>9} "
            f"{ci_text:>13} "
            f"{r['withdrawn_share']:>9.1%} {r['coverage_reported']:>8.1%} {w:>6}"
        )
    print(
        f"\nSequential test in simulation (P >= {P_REQUIRED} +- 0.05, alpha = beta = 0.05), faithful model: "
        "median runs of 300 tests"
    )
    print(f"{'version':<24} {'requirement':<40} {'truth':>6} {'fixed n':>7} {'batch 10':>14} {'batch 100':>14}")
    for r in seq:
        cells = [f"{r[b]['median_runs']:.0f} ({r[b]['vs_fixed']:.2f}x)" for b in ("batch_10", "batch_100")]
        print(
            f"{r['version']:<24} {r['requirement']:<40} {r['truth']:>6.3f} {r['fixed_n']:>7} "
            f"{cells[0]:>14} {cells[1]:>14}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "argv": sys.argv[1:],
        "seconds": time.perf_counter() - t0,
    }
    args.out.write_text(json.dumps({"meta": meta, "rows": rows, "sequential": seq}, indent=1))
    print(f"written {args.out} ({meta['seconds']:.0f} s)")


if __name__ == "__main__":
    main()

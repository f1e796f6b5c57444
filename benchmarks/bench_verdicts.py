"""How honest and how economical the goal verdicts are, on synthetic data with a known true P(goal).

Real-system part: starts x ~ N(0, 1); a real run meets the goal with p(x) = expit(2 + slope x) (slope:
how much the start decides the outcome). The model's p is expit(2 + shift + slope x), estimated from 20
simulated runs per start: faithful (shift 0), slightly wrong (shift 0.7) and badly wrong (shift -5).
Each repetition draws 10 (or 30) real runs with their paired predictions and 400 simulated starts, and runs the
whole verdict (PPI, and the control-variate variant): coverage of the nominal 95 % interval for the true
real P(goal) when the claim is kept, of the interval finally reported (the real-only Clopper-Pearson one
after a withdrawal), its width over the real-only width, and how often the claim is withdrawn.

Sequential part: Bernoulli streams with p around p_required = 0.9 (indifference +-0.05, alpha = beta =
0.05), batches of 10: runs used by the SPRT and by the any-time confidence sequence against the
fixed-size exact test with the same error rates, and the realised error rates.

Floor part: how often the old rule (all sims vs all real runs against two real halves) and the fair
matched-size permutation rule say "within the floor", for sims from the real distribution and for too
narrow sims; with ``--logs``, the same on the lane-keeping field logs (runs of one controller against the
others of that controller, and against the next controller).

    python benchmarks/bench_verdicts.py [--reps 300] [--slopes 4 6 8] [--real 10 30]
        [--out bench_out/bench_verdicts.json]
        [--logs /work/shared/data/lane-keeping-fot]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from envi_py.metrics import safety_comfort
from envi_py.verdicts import (
    Verdict,
    clopper_pearson,
    confidence_sequence,
    fair_floor,
    fixed_sample_size,
    kld_gaussian,
    ppi_verdict,
    sprt,
)

MODELS = {"faithful": 0.0, "slightly wrong": 0.7, "badly wrong": -5.0}
SIMS_PER_START, STARTS = 20, 400


def expit(z: np.ndarray) -> np.ndarray:
    return 1 / (1 + np.exp(-z))


def true_rate(slope: float) -> float:
    z, w = np.polynomial.hermite_e.hermegauss(80)
    return float(np.sum(w * expit(2 + slope * z)) / np.sqrt(2 * np.pi))


def real_system(reps: int, slope: float, n_real: int, seed: int) -> list[dict]:
    truth, rows = true_rate(slope), []
    for name, shift in MODELS.items():
        for estimator in ("ppi", "control-variate"):
            rng = np.random.default_rng(seed)
            claimed, final, ratio, withdrawn, real_cover = [], [], [], [], []
            for _ in range(reps):
                x = rng.normal(size=n_real)
                y = rng.random(n_real) < expit(2 + slope * x)
                paired = rng.binomial(SIMS_PER_START, expit(2 + shift + slope * x)) / SIMS_PER_START
                sims = rng.binomial(SIMS_PER_START, expit(2 + shift + slope * rng.normal(size=STARTS))) / SIMS_PER_START
                v = ppi_verdict(sims, y, paired, p_required=0.5, estimator=estimator, sims_per_start=SIMS_PER_START)
                lo, hi = clopper_pearson(int(y.sum()), y.size)
                real_cover.append(lo <= truth <= hi)
                final.append(v.low <= truth <= v.high)
                withdrawn.append(v.withdrawn)
                if not v.withdrawn:
                    claimed.append(v.low <= truth <= v.high)
                    ratio.append((v.high - v.low) / (hi - lo))
            rows.append(
                {
                    "slope": slope,
                    "model": name,
                    "logit_shift": shift,
                    "estimator": estimator,
                    "reps": reps,
                    "n_real": n_real,
                    "n_sim_starts": STARTS,
                    "sims_per_start": SIMS_PER_START,
                    "true_p": truth,
                    "coverage_when_claimed": float(np.mean(claimed)) if claimed else None,
                    "claims": len(claimed),
                    "coverage_final": float(np.mean(final)),
                    "coverage_real_only": float(np.mean(real_cover)),
                    "median_width_ratio": float(np.median(ratio)) if ratio else None,
                    "withdrawn_rate": float(np.mean(withdrawn)),
                }
            )
    return rows


def sequential(reps: int, seed: int) -> list[dict]:
    p_req, delta, batch = 0.9, 0.05, 10
    n_fixed, c_fixed = fixed_sample_size(p_req, delta, 0.05, 0.05)
    rows = []
    for p in (0.8, 0.85, 0.9, 0.95, 0.99):
        rng = np.random.default_rng(seed)
        s = [sprt(lambda n, p=p, rng=rng: rng.random(n) < p, p_req, delta, batch=batch) for _ in range(reps)]
        cs = [
            confidence_sequence(lambda n, p=p, rng=rng: rng.random(n) < p, p_req, batch=batch, max_runs=5000)
            for _ in range(reps)
        ]
        wrong = Verdict.PASS if p < p_req else Verdict.FAIL if p > p_req else None
        rows.append(
            {
                "p": p,
                "reps": reps,
                "batch": batch,
                "fixed_n": n_fixed,
                "fixed_critical": c_fixed,
                "sprt_median_runs": float(np.median([r.runs for r in s])),
                "sprt_mean_runs": float(np.mean([r.runs for r in s])),
                "sprt_error_rate": None if wrong is None else float(np.mean([r.verdict is wrong for r in s])),
                "sprt_interval_coverage": float(np.mean([r.low <= p <= r.high for r in s])),
                "cs_median_runs": float(np.median([r.runs for r in cs])),
                "cs_undecided_rate": float(np.mean([r.verdict is Verdict.UNDECIDED for r in cs])),
                "cs_error_rate": None if wrong is None else float(np.mean([r.verdict is wrong for r in cs])),
                "cs_interval_coverage": float(np.mean([r.low <= p <= r.high for r in cs])),
            }
        )
    return rows


def floors(reps: int, seed: int) -> list[dict]:
    """Old floor (halves of the real runs vs all sims) against the fair matched-size floor, KLD, 10 real runs.

    Per-run figures are 2-D Gaussian (like (safety, comfort)); sims are 10x the real runs, drawn from the same
    distribution ("same") or with 60 % of the real spread ("too narrow"). Old rule: the KLD of all real runs vs
    all sims at or below the mean KLD between two real halves (20 halvings), as envi_py.metrics.floor is used.
    """
    rows = []
    for name, spread in (("same", 1.0), ("too narrow", 0.6)):
        rng = np.random.default_rng(seed)
        old_pass, fair_pass, ratios = [], [], []
        for i in range(reps):
            real, sim = rng.normal(size=(10, 2)), spread * rng.normal(size=(100, 2))
            halves = [rng.permutation(10) for _ in range(20)]
            old_floor = np.mean([kld_gaussian(real[h[:5]], real[h[5:]]) for h in halves])
            old_pass.append(kld_gaussian(real, sim) <= old_floor)
            res = fair_floor(real, sim, kld_gaussian, repetitions=5, permutations=49, seed=i)
            fair_pass.append(res.within_floor)
            ratios.append(res.ratio)
        rows.append(
            {
                "sims": name,
                "spread": spread,
                "reps": reps,
                "n_real": 10,
                "n_sim": 100,
                "per_side": 5,
                "old_within_floor_rate": float(np.mean(old_pass)),
                "fair_within_floor_rate": float(np.mean(fair_pass)),
                "fair_median_ratio": float(np.median(ratios)),
                "fair_level": 0.05,
                "repetitions": 5,
                "permutations": 49,
            }
        )
    return rows


def real_log_floors(folder: Path, seed: int) -> list[dict]:
    """The floor on the lane-keeping field logs (``log_<x>_<i>.csv``: time, color, angle), (safety, comfort) KLD.

    Per controller x: the KLD between two disjoint random sets of 5 runs (the old floor's halves) and of 10
    runs (20 draws each), then the fair floor of 10 runs of x against the other runs of x (the same system:
    should be within) and against the runs of the next x (another controller: should be outside).
    """
    figures: dict[int, list[np.ndarray]] = {}
    for path in sorted(folder.glob("log_*_*.csv")):
        x = int(path.stem.split("_")[1])
        color = np.loadtxt(path, delimiter=",", skiprows=1, usecols=1, ndmin=1)
        figures.setdefault(x, []).append(color)
    keys = sorted(figures)
    sc = {x: safety_comfort(np.stack([c[: min(map(len, figures[x]))] for c in figures[x]])) for x in keys}
    rng, rows = np.random.default_rng(seed), []
    for j, x in enumerate(keys):
        runs = sc[x]
        kld = {
            size: [kld_gaussian(*np.split(runs[rng.permutation(len(runs))[: 2 * size]], 2)) for _ in range(20)]
            for size in (5, 10)
        }
        order = rng.permutation(len(runs))
        same = fair_floor(runs[order[:10]], runs[order[10:]], kld_gaussian, repetitions=10, permutations=199, seed=seed)
        row = {
            "x": x,
            "runs": len(runs),
            "kld_5_vs_5_mean": float(np.mean(kld[5])),
            "kld_10_vs_10_mean": float(np.mean(kld[10])),
            "same_controller": same.to_json(),
        }
        if j + 1 < len(keys):
            row["next_controller"] = fair_floor(
                runs[order[:10]], sc[keys[j + 1]], kld_gaussian, repetitions=10, permutations=199, seed=seed
            ).to_json()
        rows.append(row)
    return rows


def _f(x: float | None, fmt: str = ".3f") -> str:
    return "-" if x is None else format(x, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument(
        "--slopes", type=float, nargs="+", default=[4.0, 6.0, 8.0], help="how strongly the start decides the outcome"
    )
    ap.add_argument("--real", type=int, nargs="+", default=[10, 30], help="real runs per repetition")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("bench_out/bench_verdicts.json"))
    ap.add_argument("--logs", type=Path, default=None, help="folder of lane-keeping field logs for the floor part")
    args = ap.parse_args()
    t0 = time.time()
    rs = [r for n in args.real for slope in args.slopes for r in real_system(args.reps, slope, n, args.seed)]
    print(
        f"Real system: {STARTS} simulated starts x {SIMS_PER_START} sims, {args.reps} repetitions per row, "
        f"nominal 95 %; 'cover|claim': coverage of the true P(goal) when the claim is kept, 'cover final': of "
        f"the interval reported (real-only after a withdrawal), 'cover CP': real-only Clopper-Pearson"
    )
    print(
        f"{'real':>4} {'slope':>5} {'true p':>6} {'model':<15} {'estimator':<16} {'cover|claim':>11} "
        f"{'cover final':>11} {'cover CP':>8} {'width/CP':>8} {'withdrawn':>9}"
    )
    for r in rs:
        print(
            f"{r['n_real']:>4} {r['slope']:>5g} {r['true_p']:>6.3f} {r['model']:<15} {r['estimator']:<16} "
            f"{_f(r['coverage_when_claimed']):>11} {_f(r['coverage_final']):>11} {_f(r['coverage_real_only']):>8} "
            f"{_f(r['median_width_ratio']):>8} {_f(r['withdrawn_rate']):>9}"
        )
    sq = sequential(args.reps, args.seed)
    print(
        f"\nSequential, p_required 0.9 +- 0.05, alpha = beta = 0.05, batches of 10, {args.reps} repetitions; "
        f"fixed-size exact test: n = {sq[0]['fixed_n']}"
    )
    print(
        f"{'p':>5} {'SPRT med':>8} {'SPRT mean':>9} {'SPRT/fixed':>10} {'SPRT err':>8} {'CS med':>7} "
        f"{'CS undec':>8} {'CS err':>6} {'CS cover':>8}"
    )
    for r in sq:
        print(
            f"{r['p']:>5.2f} {r['sprt_median_runs']:>8.0f} {r['sprt_mean_runs']:>9.1f} "
            f"{r['sprt_median_runs'] / r['fixed_n']:>10.2f} {_f(r['sprt_error_rate']):>8} {r['cs_median_runs']:>7.0f} "
            f"{r['cs_undecided_rate']:>8.3f} {_f(r['cs_error_rate']):>6} {r['cs_interval_coverage']:>8.3f}"
        )
    fl = floors(min(args.reps, 100), args.seed)
    print(
        f"\nFloor, KLD of 2-D Gaussian fits, 10 real runs, 100 sims, {fl[0]['reps']} repetitions: how often each rule "
        f"says 'within the floor' (fair: permutation p > 0.05, test at 10 vs 10 runs, ratio at 5 vs 5)"
    )
    print(f"{'sims':<11} {'old rule':>8} {'fair rule':>9} {'fair ratio':>10}")
    for r in fl:
        print(
            f"{r['sims']:<11} {r['old_within_floor_rate']:>8.3f} {r['fair_within_floor_rate']:>9.3f} "
            f"{r['fair_median_ratio']:>10.2f}"
        )
    logs = []
    if args.logs is not None:
        logs = real_log_floors(args.logs, args.seed)
        print(
            f"\nFloor on the field logs in {args.logs}, KLD of (safety, comfort) Gaussian fits; fair test: 10 runs "
            f"of x against the other runs of x (same) and against the runs of the next x (next)"
        )
        print(
            f"{'x':>3} {'runs':>4} {'KLD 5v5':>8} {'KLD 10v10':>9} {'same p':>7} {'same ratio':>10} "
            f"{'next p':>7} {'next ratio':>10}"
        )
        for r in logs:
            nxt = r.get("next_controller")
            print(
                f"{r['x']:>3} {r['runs']:>4} {r['kld_5_vs_5_mean']:>8.2f} {r['kld_10_vs_10_mean']:>9.2f} "
                f"{r['same_controller']['p_value']:>7.3f} {_f(r['same_controller']['ratio'], '.2f'):>10} "
                f"{(_f(nxt['p_value']) if nxt else '-'):>7} {(_f(nxt['ratio'], '.2f') if nxt else '-'):>10}"
            )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "reps": args.reps,
                "slopes": args.slopes,
                "n_real": args.real,
                "seed": args.seed,
                "seconds": time.time() - t0,
                "real_system": rs,
                "sequential": sq,
                "floor": fl,
                "field_log_floor": logs,
            },
            indent=1,
        )
    )
    print(f"\nwrote {args.out} ({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()

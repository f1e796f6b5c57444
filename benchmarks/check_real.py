"""``envi check`` on the real lane-keeping logs: 3 real runs per version plus simulation, beside all runs.

Usage: ``python benchmarks/check_real.py [--draws 10] [--quick] [--out bench_out/check_real.json]``.

A BC model (envi's defaults) is trained on the first 20 logs of x = 10, 30, 50 (5 more, after a gap
of one log, for selection). Each version's remaining logs after one more gap are its test block
(x = 20 and 40 are never trained on). For each of ``--draws`` random triples of test logs per
version, :func:`envi_py.check.check` gives the verdict on the description's requirement
(``max_abs_dev(color, 40) <= 35`` with P >= 0.9) from those 3 real runs plus the model (PPI, started
from the triple and from every other log of the test block: their outcomes are not used), and from
simulation alone (SPRT). Beside it: the exact (Clopper-Pearson) interval from ALL real runs of the
version (40 or 66 logs: consecutive slices of one run, so a little narrower than independent runs
would make it). Printed per version: the all-runs interval, the median model+3-real interval, how
many draws kept the model's claim, how often the reported interval contains the all-runs estimate,
and the verdicts.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envi_py.check import check, requirements_of
from envi_py.goals.evaluate import signals_of
from envi_py.goals.requirements import parse, satisfied
from envi_py.logs import load_logs
from envi_py.system import lane_keeping
from envi_py.train import train
from envi_py.verdicts import clopper_pearson

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "lane-keeping-fot"
TRAIN_X = (10, 30, 50)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--draws", type=int, default=10, help="random triples of real runs per version")
    ap.add_argument("--real", type=int, default=3, help="real runs per version in each check")
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--quick", action="store_true", help="30 epochs, 2 draws")
    ap.add_argument("--out", type=Path, default=Path("bench_out/check_real.json"))
    args = ap.parse_args()
    if args.quick:
        args.epochs, args.draws = 30, 2
    torch.set_num_threads(1)
    system = lane_keeping().with_pattern("log_{x}_{run}.csv")
    logs = load_logs(args.data, system, min_length=11)
    by_x: dict[float, list] = {}
    for lg in sorted(logs, key=lambda lg: (lg.param["x"], int(lg.meta.run_id.rsplit("_", 1)[-1]))):
        by_x.setdefault(lg.param["x"], []).append(lg)
    train_logs = [lg for x in TRAIN_X for lg in by_x[x][:20]]
    val_logs = [lg for x in TRAIN_X for lg in by_x[x][21:26]]
    t0 = time.perf_counter()
    ckpt = train("bc", train_logs, val_logs, system=system, epochs=args.epochs, seed=0)
    train_s = time.perf_counter() - t0
    spec = requirements_of(system, [])[0]
    req = parse(spec, [c.name for c in system.schema.channels])
    rng = np.random.default_rng(0)
    rows = []
    for x, all_logs in by_x.items():
        test = all_logs[27:]
        runs = signals_of(all_logs, all_logs[0].meta.schema, ckpt.config.history, ckpt.period_ms)
        k = int(satisfied(req, runs).sum())
        truth_low, truth_high = clopper_pearson(k, len(all_logs), 0.95)
        p_all = k / len(all_logs)
        draws = []
        for d in range(args.draws):
            pick = rng.choice(len(test), args.real, replace=False)
            real = [test[i] for i in pick]
            others = [lg for i, lg in enumerate(test) if i not in set(pick.tolist())]
            (row,) = check(ckpt, real, [spec], extra_starts=others, seed=d)
            r = row.real_system
            draws.append(
                {
                    "verdict": r["verdict"],
                    "basis": r["basis"],
                    "interval": r["interval"],
                    "sim_verdict": row.simulation["verdict"],
                    "sim_runs": row.simulation["runs"],
                    "covers_all_runs": r["interval"][0] <= p_all <= r["interval"][1],
                }
            )
        kept = [dr for dr in draws if dr["basis"] == "model+real"]
        rows.append(
            {
                "x": x,
                "role": "trained" if x in TRAIN_X else "unseen",
                "all_runs": {"n": len(all_logs), "satisfied": k, "p": p_all, "interval": [truth_low, truth_high]},
                "test_block": len(test),
                "draws": draws,
                "kept": len(kept),
                "median_interval": np.median([dr["interval"] for dr in draws], axis=0).tolist(),
                "covers_all_runs": float(np.mean([dr["covers_all_runs"] for dr in draws])),
                "verdicts": dict(Counter(dr["verdict"] for dr in draws)),
                "sim_verdicts": dict(Counter(dr["sim_verdict"] for dr in draws)),
            }
        )
    print(
        f"requirement: {spec.name}: {spec.expr} with P >= {spec.probability}; model: BC trained on x = 10, 30, 50 "
        f"({args.epochs} epochs, {train_s:.0f} s); {args.draws} draws of {args.real} real runs per version"
    )
    print(
        f"{'x':>4} {'role':<8} {'all runs: P [95%]':<28} {'model+3 real: median [95%]':<28} {'kept':>5} "
        f"{'covers':>7}  verdicts (real system) | sim only"
    )
    for r in rows:
        a, m = r["all_runs"], r["median_interval"]
        print(
            f"{r['x']:>4g} {r['role']:<8} {a['p']:.2f} [{a['interval'][0]:.2f}, {a['interval'][1]:.2f}] n={a['n']:<8} "
            f"[{m[0]:.2f}, {m[1]:.2f}]{'':<16} {r['kept']:>2}/{args.draws} {r['covers_all_runs']:>6.0%}  "
            f"{r['verdicts']} | {r['sim_verdicts']}"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.platform(), "cpus": os.cpu_count(), "argv": sys.argv[1:], "train_seconds": train_s}
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1, default=float))
    print(f"written {args.out}")


if __name__ == "__main__":
    main()

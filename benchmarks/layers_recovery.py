"""Effect layers on a world family with a known injected effect: is the injected value recovered, and
does the layer close the gap on confirmation logs?

Per seed and case: a small BC model of the clean world (the validation's tiny size), 12 logs with
the effect to fit the layer of the effect's own candidate (the diagnosis is bypassed, so this
measures the layer, not the ranking), 12 other logs to confirm it, and 12 clean logs of the model's
own world: how close the model alone comes to their floor (a layer adds the effect, not what the
model misses on its own world). A one-step fit whose windows lie outside the clean training windows
is an extrapolation, reported as not identifiable (its interval is the whole grid), and its coverage
of the injected value is not scored. Prints a markdown table and writes JSON.

    PYTHONPATH=. python benchmarks/layers_recovery.py --world diffdrive --seeds 2 [--out bench_out/layers_recovery.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from envi_py.diagnose.layers import fit_and_confirm
from envi_py.diagnose.validate import ALL_CASES, covers, injected_layer, world_logs
from envi_py.train import train

CASES = ("delay", "delay_x50", "lag", "noise", "quantise", "saturation", "backlash")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", default="diffdrive", choices=("steered", "diffdrive"))
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--out", default="bench_out/layers_recovery.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    by = {c.name: c for c in ALL_CASES}
    rows, models, clean = [], {}, {}
    for seed in range(args.seeds):
        for name in args.cases:
            case = by[name]
            start = time.time()
            key = (seed, case.controller.to_json().__repr__(), case.history or 4)
            if key not in models:
                fit = world_logs(args.world, case.controller, 15, 100, {}, seed)
                clean[key] = fit[:12]
                models[key] = train("bc", fit[:12], fit[12:], seed=seed, epochs=80, lr=1e-3, history=case.history or 4)
            ckpt = models[key]
            shown = world_logs(args.world, case.controller, 12, 100, case.effects, seed + 1_000)
            other = world_logs(args.world, case.controller, 12, 100, case.effects, seed + 2_000)
            held_out = world_logs(args.world, case.controller, 12, 100, {}, seed + 3_000)  # its own world's
            r = fit_and_confirm(
                ckpt, case.expected, shown, other, runs=2, seed=seed, boot=200, train_logs=clean[key], own_logs=held_out
            )
            assert r is not None
            truth = injected_layer(case, ckpt.period_ms)
            c = r["confirm"]
            rows.append(
                {
                    "world": args.world,
                    "case": name,
                    "seed": seed,
                    "fitted": r["fit"]["short"],
                    "support": r["fit"]["support"],
                    "injected": truth,
                    "identifiable": r["fit"]["identifiable"],
                    "covered": bool(covers(r["fit"], truth)),
                    "shrink": c["shrink"],
                    "shrink_ci": c["shrink_ci"],
                    "before_over_floor": c["before"] / c["floor"],
                    "after_over_floor": c["after"] / c["floor"],
                    "within_1.5_floor": c["within_1.5_floor"],
                    "own_over_floor": r["own"]["ratio"],
                    "within_1.5_own": r["own"]["within_1.5_own"],
                    "seconds": time.time() - start,
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    print(f"\n{args.world}, {args.seeds} seed(s) per case\n")
    print(
        "| case | seed | injected | fitted [interval] | covers | before / floor | after / floor | "
        "model alone on held-out clean logs / their floor | shrink [95% CI] |"
    )
    print("|---|---:|---|---|---|---:|---:|---:|---|")
    for r in rows:
        inj = f"{r['injected'][0]} {r['injected'][1]:g}" if r["injected"] else "-"
        lo, hi = r["shrink_ci"]
        print(
            f"| {r['case']} | {r['seed']} | {inj} | {r['fitted']} | {coverage_cell(r)} | "
            f"{r['before_over_floor']:.1f} | {r['after_over_floor']:.1f} | {own_cell(r['own_over_floor'])} | "
            f"{r['shrink']:+.0%} [{lo:+.0%}, {hi:+.0%}] |"
        )
    known = [r for r in rows if r["identifiable"]]
    within = np.mean([r["within_1.5_floor"] for r in rows])
    scored = [r["within_1.5_own"] for r in rows if r["within_1.5_own"] is not None]
    print(
        f"\n{len(rows) - len(known)} of {len(rows)} fits not identifiable (extrapolations); the interval of the "
        f"other {len(known)} covers the injected value in {sum(r['covered'] for r in known)}; within 1.5x floor "
        f"{within:.0%} of {len(rows)} trials; within 1.5x of the model's own level on held-out clean logs (or "
        f"the floor) {sum(scored)} of {len(scored)} (the rest: held-out runs that do not vary, floor 0)"
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1) + "\n")


def own_cell(ratio: float | None) -> str:
    """The model alone on held-out clean logs over their floor; 'floor 0' when those runs do not vary."""
    return "floor 0" if ratio is None else f"{ratio:.1f}"


def coverage_cell(r: dict) -> str:
    """Whether the interval covers the injected value; '-' for a fit that is not identifiable."""
    return ("yes" if r["covered"] else "no") if r["identifiable"] else "-"


if __name__ == "__main__":
    main()

"""Seconds per training epoch of BC, GAIL and BCxGAIL at n=30 logs, and the default TOVK grid's wall time.

Usage: ``python benchmarks/bench_training.py [--data DIR] [--epochs 10] [--grid-reps 1] [--out bench.json]``.

Per-epoch times exclude the closed-loop validation (it runs every 10 epochs and is timed
separately). The TOVK grid time is *measured* on ``--grid-reps`` repetitions of the default grid
(random, bc, gail, bcxgail x n = 3, 15, 30, 300 epochs) and extrapolated linearly to 5
repetitions, which is exact up to scheduling since repetitions are independent equal-sized jobs;
``--grid-reps 0`` skips it and estimates from the per-epoch figures instead. One torch thread per
process, as the experiment workers use.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envi_py.logs import load_logs  # noqa: E402
from envi_py.system import lane_keeping  # noqa: E402
from envi_py.train.common import closed_loop_score, model_config, new_checkpoint  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "lane-keeping-fot"


def time_bc(logs, epochs: int) -> float:
    from envi_py.train.bc import bc_loss

    ckpt = new_checkpoint("bc", logs, [], model_config(logs), 0, {})
    data = ckpt.dataset(logs)
    xs, ys = [torch.tensor(x) for x in data.X], [torch.tensor(y) for y in data.Y]
    opt = torch.optim.Adam(ckpt.model.parameters(), lr=5e-5)
    t0 = time.perf_counter()
    for _ in range(epochs):
        for x, y in zip(xs, ys):  # one step per log, as train_bc
            loss = bc_loss(ckpt.model, x, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
    return (time.perf_counter() - t0) / epochs


def time_gail(logs, epochs: int, bc_weight: float) -> float:
    from envi_py.train.gail import GailConfig, _Trainer

    ckpt = new_checkpoint("gail", logs, [], model_config(logs, head="gaussian"), 0, {})
    trainer = _Trainer(ckpt, logs, GailConfig(bc_weight=bc_weight), 0)
    trainer.epoch()  # warm-up
    t0 = time.perf_counter()
    for _ in range(epochs):
        trainer.epoch()
    return (time.perf_counter() - t0) / epochs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--epochs", type=int, default=10, help="epochs timed per algorithm")
    ap.add_argument("--grid-reps", type=int, default=1, help="TOVK grid repetitions to measure (0: estimate)")
    ap.add_argument("--grid-epochs", type=int, default=300)
    ap.add_argument("--out", default="bench_training.json")
    args = ap.parse_args()
    torch.set_num_threads(1)
    pool = load_logs(args.data, lane_keeping().with_pattern("log_{x}_{run}.csv"), where={"x": [30]}, min_length=11)
    logs, val = pool[:30], pool[30:33]
    rows = {
        "bc": time_bc(logs, args.epochs),
        "gail": time_gail(logs, args.epochs, 0.0),
        "bcxgail": time_gail(logs, args.epochs, 1.0),
    }
    ckpt = new_checkpoint("bc", logs, val, model_config(logs), 0, {})
    t0 = time.perf_counter()
    closed_loop_score(ckpt, val)
    eval_s = time.perf_counter() - t0
    result = {
        "n_logs": len(logs),
        "seconds_per_epoch": rows,
        "validation_seconds": eval_s,
        "authors_seconds_per_epoch": {"bc": 0.2, "gail": 2.5},
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    print(f"{'algorithm':<10} {'s/epoch':>9} {'authors':>9}")
    for k, v in rows.items():
        a = result["authors_seconds_per_epoch"].get(k)
        print(f"{k:<10} {v:>9.4f} {a if a is not None else '-':>9}")
    print(f"closed-loop validation on {len(val)} logs: {eval_s:.3f} s (every 10 epochs)")
    if args.grid_reps > 0:
        from envi_py.experiments.run import run_experiment

        t0 = time.perf_counter()
        run_experiment(
            pool,
            ["tovk"],
            Path(args.out).with_suffix("") / "grid",
            reps=args.grid_reps,
            epochs=args.grid_epochs,
            progress=False,
        )
        measured = time.perf_counter() - t0
        result["tovk_grid"] = {
            "measured_reps": args.grid_reps,
            "measured_seconds": measured,
            "extrapolated_5_reps_seconds": measured * 5 / args.grid_reps,
            "workers": os.cpu_count(),
            "epochs": args.grid_epochs,
        }
        print(
            f"TOVK grid, {args.grid_reps} repetition(s) measured: {measured:.0f} s -> 5 repetitions "
            f"(extrapolated): {measured * 5 / args.grid_reps:.0f} s"
        )
    else:
        per_rep = sum(args.grid_epochs * (rows[a] * n / 30 + eval_s / 10) for a in rows for n in (3, 15, 30))
        workers = os.cpu_count() or 1
        result["tovk_grid"] = {
            "estimated_5_reps_seconds": 5 * per_rep / workers,
            "workers": workers,
            "method": "per-epoch time scaled linearly in n, plus validation; not measured",
        }
        print(f"TOVK grid, 5 repetitions, estimated (not measured): {5 * per_rep / workers:.0f} s on {workers} workers")
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

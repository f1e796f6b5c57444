"""Closed-loop fidelity of envi's models of the car twin (issue 14's done-when), per version.

Usage: ``python benchmarks/fidelity_car.py [--quick] [--configs bc,bc-res,twin] [--seed 0] [--n 20]
[--test 20] [--test-sets 2] [--save-dir D] [--load-dir D] [--out bench_out/fidelity_car.json]``.

Protocol. The car twin (:mod:`envi_py.twin.car`) gives field logs of five controller versions
(gains): three are trained on (TMVK) and two are never seen (TMVU). A model is trained on ``n``
logs per trained version (``--n``, 20) with 5 more per version for model selection. It is then
verified on ``--test-sets`` independent sets of ``--test`` fresh logs of every version (other seeds,
so other lanes and leads): each test log's sigma_0 starts ``--sims`` simulated runs on the native
engine, and :func:`envi_py.verify.verify` compares the goal metrics of the car description (lane
deviation, closest approach, gap error) at matched sizes: W1 between a real half and as many
simulated runs, over W1 between the two real halves (the fair floor, ``m = test // 2`` runs per
side, 10 random splits), and the permutation test with all real runs against as many simulated ones.

Target (issue 14): every goal's ratio within 1.5 for every version, TMVK and TMVU, and no simulated
run diverging (a state held at a limit of its range, or beyond the training data's, for a tenth of
the run, counted against the real runs by the same rule: :func:`envi_py.goals.selection.diverged_fraction`).
The ratio is averaged over the test sets, and its spread across them is printed beside it, since
the floor itself rests on 10 runs per side; the JSON also holds the pooled ratio (summed matched W1
over summed floor W1), which one set's near-zero floor cannot blow up. Divergence is reported two
ways: "held", the rule above, with Fisher's one-sided p of "simulated runs hold more often than
real" (pooled over sets), and "runaway", the same rule at the limits the simulator clamps to (the
training range, where a collapsing state comes to rest unseen by the first rule) with a saturating
sensor's limit reading taken out: a state where real runs never go. Config ``twin`` is the twin
itself as the model (fresh field runs in place of simulated ones): what a perfect model scores
under the same statistic.
Models that are not plain MLPs (a residual head, derived channels) are simulated with the PyTorch
engine, plain ones with the native engine.

Measured (2 test sets x 20 logs per version, 2 simulated runs per test log, seed 0, 2026-11-24):
``bc`` worst ratio 10.3 (closest approach of kp_speed 50: its simulated distance crept 1 cm a step
toward the lead and collapsed to 11 cm against 23 real); ``bc-res`` worst 2.14, 12 of 15 cells
within 1.5, no exchangeability test below p 0.3 (the rest: lane deviation 1.54 and 1.58, closest
approach of kp_speed 50 2.14, from a few simulated runs in the tails); with ``--seed 1`` worst 3.89,
9 of 15 within 1.5, no p below 0.16 (``bc`` was not re-run at seed 1). Tried and not better than
``bc``: 600 epochs (worst 6.0), the 10-step unrolled loss (11.1; with the residual head 14.4),
input noise of one step (9.5).

Measured again (4 test sets of 20 logs per version, 2026-11-24; commands and tables in the carfid log).
The target is met by no model at any training seed, and not by a perfect one either: ``twin`` on
the same 4 sets has worst 2.18 (closest approach of kp_speed 50), and over 20 test sets a perfect
model meets "all 15 cells within 1.5" in 24 % of 2-set draws and 21 % of 4-set draws by the mean of
per-set ratios (40 % and 59 % by the pooled ratio): per-set ratios of closest approach and gap error
of kp_speed 50 reach 12 and 17, from halves of 10 runs that hold the few far-start runs unevenly.
The models have a real excess all the same. Worst ratio (mean of ratios; pooled) and simulated runs
that run away, of 800, at training seeds 0-3: ``bc-res`` 1.81, 6.08, 3.36, 6.08 (pooled 1.83, 3.41,
2.67, 2.92), run away 7, 139, 0, 410 (the distance collapses onto its 12 cm clamp);
``bc-res-noise05`` 2.67, 1.65, 4.54, 1.86 (pooled 2.39, 1.64, 2.69, 1.87), run away 0, 0, 0, 1;
real runs never run away (0 of 1600) and no config holds 255 more often than real (Fisher p >= 0.11).
The seed moves the worst ratio more than any setting does. Even the best models miss in the tails:
1.6-1.9 % of simulated runs never re-acquire the lead (none real); a window of 10 rows all at 255
cannot say how long the echo has been lost. Not better at seeds 0 and 1: history 20 (worst 6.50,
6.26), lr 3e-4 (6.07, 6.08), 10 selection runs with patience 20 (the same epochs), a training batch
with typical far-start coverage (``--train-seed 334``: 8.72, 4.65). ``bc`` at seed 0 under the
same protocol: worst 5.01, 10 cells above. Tried in the selection and undone: keeping the last
evaluations only on complete smoothing windows (seed 1 then kept epoch 70: worst 11.1), and marking
epochs whose simulated runs rest on a clamp limit as diverged (seeds 1 and 3: 139 and 410 collapsed
runs became 12 and 30, but seed 0 lost its good epoch: worst 6.48).

Measured with 20 test sets (2026-11-24; ``--configs bc-res-noise05 --test-sets 20 --load-dir``
the seed's saved models, and ``--configs twin --test-sets 20``), pooled ratio, worst cell: the twin
itself 1.33 (no cell above 1.5; its worst cell's single-set ratios average 2.56 and reach 12.4);
the default training at seeds 0-3: 2.20, 1.33, 2.52, 1.64 (7, 0, 5, 2 cells above 1.5; 0, 0, 8, 6
of 4,000 simulated runs run away, against 2 of 2,000 real runs by the same rule); the four as a
run-level mixture (``--mixture`` of the four folders, ``--sims 1``): 1.496, 7 of 8,000 run away.
The seeds' selection scores (0.034, 0.026, 0.024, 0.026) do not rank their test ratios.

Measured on this machine (2026-11-28, ``--configs default --seed S --test-sets 20 --sims 1``), with a
saturating sensor's value-head draws clamped to its in-range readings (12-152 cm; before: to 255):
worst pooled ratio at seeds 0-3 1.93, 1.92, 2.22, 1.39 (before 2.44, 3.95, 1.98, 2.10), cells above
1.5 2, 2, 6, 0 (before 7, 5, 7, 5), runs run away 4, 56, 47, 0 of 2,000 (before 4, 56, 7, 6); seed 3
meets the target. ``default-ens3`` at seed 0 (3 members), with the clamp of before: worst 2.99, 26 run away;
with the new clamp 2.07, 33 run away. Then with 10 simulated runs per validation log (the car's
``[training] select_runs``, was 5): worst 1.93, 1.80, 2.02, 1.39, cells above 1.5 2, 3, 5, 0, runs run
away 4, 1, 12, 0 of 2,000 (seeds 0 and 3 keep the same epoch).

Measured again at 514e219 (2026-11-29, ``--configs default-context,default --seed S --test-sets 20
--sims 1``, seeds 0-3, one process per seed): ``default`` worst pooled ratio 1.47, 2.51, 1.69, 1.74
(cells above 1.5: 0, 5, 2, 1; runs run away 13, 38, 5, 8 of 2,000; epochs 180, 160, 80, 50). These are
not the figures above at the same seeds: the selection's limit tolerance (9c1700c) moved the chosen
epochs, and the seed still moves the worst ratio more than any setting. ``default-context`` (sigma_0's
per-run mean and spread as an input all run long) 1.82, 1.23, 1.10, 2.16 (cells above 1, 0, 0, 5; run
away 10, 1, 2, 9): two seeds of four meet the ratio target against one, 22 runaways against 64 of
8,000, but the worst seed is worse; four seeds do not decide it, so the car's description does not
ship it. On the lane-keeping real logs it is worse (``fidelity_real.py --algorithms
bc-default,bc-context --n 3,20 --folds 3``: mean KLD 0.97 against 0.88 at n = 3, 1.06 against 0.75 at
n = 20).

Measured on this machine (2026-12-01, ``--configs default,default-constant --seed S --test-sets 20
--sims 1``, seeds 0-7; ``default`` now anneals BC's step size along a cosine over the 300 epochs and
trains to that cap, the car's ``[training] lr_schedule``): worst pooled ratio 1.50, 1.29, 1.37, 1.20,
1.43, 1.44, 1.41, 1.56 (cells above 1.5: 0 at seeds 0-6, 1 at seed 7; the worst cell is the closest
approach of kp_speed 50 at every seed, where the twin itself scores 1.33 [1.08, 1.86]), runs run away
2, 0, 0, 0, 0, 0, 2, 0 of 2,000 (real: 2 of 2,000). ``default-constant`` (the constant step of
before, early stopping after 10 evaluations): 4.04, 1.57, 1.64, 2.52, 1.83, 3.50, 2.06, 1.59 (cells
above 1.5: 9, 1, 1, 4, 5, 9, 4, 1), runs run away 10, 0, 12, 4, 0, 4, 11, 1. These constant-step
figures are not the 2026-11-29 ones at the same seeds (seed 0 was 1.47 there): the same code,
514e219, trains the bit-identical 4.04 model here, so the constant step's outcome moved with the
machine's arithmetic. The cosine step did not: with ``ATEN_CPU_CAPABILITY=avx2`` seeds 0 and 3
give 1.49 and 1.48 (3 and 3 runs run away). Why it helps: at a constant step of 1e-3 the validation
score jumped between neighbouring evaluations (0.02 to 0.2 and back within 30 epochs at every seed),
so the epoch kept was one draw of a chaotic walk; annealed, the last 50 epochs change the closed
loop little and the selection keeps one of them (epochs 260-300 at every seed). Stopped early by the
constant step's patience, seeds 2 and 3 kept epochs 110 and 90 (the step still at 70-80 % of its
start) and scored 1.95 and 1.71, 22 runs run away at seed 3; hence trained to the cap.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from envi_py.goals.evaluate import signals_of
from envi_py.goals.selection import diverged_fraction, runaway_states
from envi_py.logs import Log
from envi_py.model import Checkpoint
from envi_py.simulate import simulate_versions
from envi_py.system import Channel, load_system
from envi_py.train import train
from envi_py.train.common import SelectionSettings, limit_events, observed_limits
from envi_py.twin.car import CAR_TRAINED, CAR_UNSEEN, generate_car_versions
from envi_py.verify import verify

#: the twin itself as the model (fresh field runs as the simulated ones): how a perfect model scores
TWIN = "twin"
#: name -> (envi algorithm, extra training keywords); the first is envi's default
#: every config starts from envi's plain model, whatever the car description's [training] recommends;
#: ``default`` alone takes the description's defaults (residual head, input noise 0.5)
CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "default": ("bc", {}),
    "bc": ("bc", {}),
    "bc-lr5e-5": ("bc", {"lr": 5e-5}),  # the paper's lr, envi's default before
    "bc-e600": ("bc", {"epochs": 600}),
    "bcxgail": ("bcxgail", {}),
    "bc-ms10": ("bc", {"multistep": 10}),  # plus the loss of 10-step unrolls on its own predictions
    "bc-e600-ms10": ("bc", {"epochs": 600, "multistep": 10}),
    "bc-noise1": ("bc", {"input_noise": 1.0}),  # window states perturbed by about one logged step
    "bc-ms10-noise1": ("bc", {"multistep": 10, "input_noise": 1.0}),
    "bc-res": ("bc", {"residual": True}),  # the mean head predicts the change from the last state
    "bc-res-ms10": ("bc", {"residual": True, "multistep": 10}),
    "bc-res-h20": ("bc", {"residual": True, "history": 20}),  # a window that sees more of a lost echo
    "bc-res-lr3e-4": ("bc", {"residual": True, "lr": 3e-4}),
    "bc-res-noise05": ("bc", {"residual": True, "input_noise": 0.5}),  # no collapse onto the clamp at 4 seeds
    "bc-res-wide": ("bc", {"residual": True, "hidden": (512, 512)}),
    "default-context": ("bc", {"context": True}),  # the description's defaults plus sigma_0's per-run context
    # the description's defaults as a seed ensemble of 4 (envi train --members 4): each run from one member
    "default-ens4": ("bc", {"members": 4}),
    "default-ens3": ("bc", {"members": 3}),  # as lane keeping's default
    # the car's default before its cosine step size: a constant step, stopped after 10 evaluations without progress
    "default-constant": ("bc", {"lr_schedule": "constant"}),
    # the description's defaults with a fitted step-noise shape instead of normal draws (lane keeping's tails)
    "default-student-t": ("bc", {"step_noise": "student-t"}),
    "default-two-scale": ("bc", {"step_noise": "two-scale"}),
    # twice the selection's simulated runs per validation log, twice its patience: a less noisy choice of epoch
    "bc-res-sel": ("bc", {"residual": True, "selection": SelectionSettings(runs=10, patience=20)}),
    TWIN: ("none", {}),
}
TARGET = 1.5


def versions_logs(runs: int, seed: int, versions: tuple[int, ...]) -> list[Log]:
    return generate_car_versions(runs, seed=seed, versions=list(versions))


@dataclass(frozen=True)
class Scoring:
    """What the divergence rules need of a model (or, for the twin itself, of its training logs)."""

    states: tuple[Channel, ...]
    observed: dict[str, tuple[float, float]]  # each state's range in the training data
    limit_readings: tuple[tuple[int, float], ...]  # (state index, reading) of saturating sensors
    clamp: tuple[tuple[float, float], ...]  # per state, the range simulated states are clamped to
    skip: int
    period_ms: float


def pooled_interval(matched: Any, floor: Any, seed: int = 0) -> list[list[float]] | None:
    """Per goal, the 95 % BCa bootstrap interval of the pooled ratio sum(matched) / sum(floor), resampling
    whole test sets (each set's matched and floor W1 together): how far the pooled figure would move on
    other test sets (None for a single set)."""
    m, f = np.asarray(matched, dtype=float), np.asarray(floor, dtype=float)
    if m.shape[0] < 2:
        return None
    out = []
    for g in range(m.shape[1]):
        res = stats.bootstrap(
            (m[:, g], f[:, g]),
            lambda a, b, axis=-1: a.sum(axis=axis) / b.sum(axis=axis),
            paired=True,
            vectorized=True,
            n_resamples=2000,
            random_state=seed,
        )
        out.append([float(res.confidence_interval.low), float(res.confidence_interval.high)])
    return out


def scoring_of_model(ckpt: Any) -> Scoring:
    states = tuple(ckpt.schema.states)
    observed = {c.name: (float(ckpt.norm.low[i]), float(ckpt.norm.high[i])) for i, c in enumerate(states)}
    clamp = tuple(zip(*(lim.tolist() for lim in ckpt.limits())))
    return Scoring(states, observed, tuple(ckpt.config.limit_events), clamp, ckpt.config.history, ckpt.period_ms)


def scoring_of_logs(train_logs: list[Log], skip: int) -> Scoring:
    states = tuple(train_logs[0].meta.schema.states)
    ranges = observed_limits(train_logs)
    observed = {c.name: ranges[i] for i, c in enumerate(states)}
    period = float(np.median(np.diff(train_logs[0].time)))
    return Scoring(states, observed, limit_events(train_logs), tuple(ranges), skip, period)


def divergence(real: list[Log], sim: list[Log], sc: Scoring) -> dict[str, int]:
    """Counts of runs that diverge, simulated and real: by the model selection's rule
    (:func:`envi_py.goals.selection.diverged_fraction`: a state at a limit of its range, or beyond the
    training data's, for a tenth of the run) and by the same rule at the limits the simulator clamps
    to, without the saturating sensor's limit reading (:func:`envi_py.goals.selection.runaway_states`,
    as ``envi check`` counts): a state where real runs never go."""
    out = {"sim_runs": len(sim), "real_runs": len(real)}
    runaway = runaway_states(sc.states, sc.clamp, sc.limit_readings)
    for rule, states in (("held", list(sc.states)), ("runaway", runaway)):
        for side, logs in (("sim", sim), ("real", real)):
            runs = signals_of(logs, logs[0].meta.schema, sc.skip, sc.period_ms)
            out[f"{side}_{rule}"] = round(diverged_fraction([runs], states, sc.observed, None, 0.05) * len(logs))
    return out


def model_of(name: str, args: argparse.Namespace, train_logs: list[Log], system: Any) -> tuple[Any, float]:
    """The config's model: loaded from ``--load-dir`` when there, else trained (and its seconds)."""
    algorithm, extra = CONFIGS[name]
    if args.load_dir is not None and (args.load_dir / f"{name}.pt").exists():
        return Checkpoint.load(args.load_dir / f"{name}.pt"), float("nan")
    val_logs = versions_logs(5, 200, tuple(CAR_TRAINED))
    t0 = time.perf_counter()
    if not name.startswith("default"):  # the plain model plus the config's own changes
        plain = {"residual": False, "input_noise": 0.0} if algorithm == "bc" else {"residual": False}
        extra = {**plain, **extra}
    jobs = os.cpu_count() or 1  # an ensemble's members trained at once
    ckpt = train(algorithm, train_logs, val_logs, system=system, seed=args.seed, epochs=args.epochs, jobs=jobs, **extra)
    seconds = time.perf_counter() - t0
    if args.save_dir is not None:
        ckpt.save(args.save_dir / f"{name}.pt")
    return ckpt, seconds


def run_config(name: str, args: argparse.Namespace) -> dict[str, Any]:
    algorithm, extra = CONFIGS[name]
    system = load_system("car")
    trained = tuple(CAR_TRAINED)
    train_logs = versions_logs(args.n, args.train_seed, trained)
    if name == TWIN:
        members, train_s = [], 0.0
    elif args.mixture:  # a run-level ensemble: every folder's <config>.pt simulates from every test log
        members, train_s = [Checkpoint.load(d / f"{name}.pt") for d in args.mixture], float("nan")
    else:
        ckpt, train_s = model_of(name, args, train_logs, system)
        members = [ckpt]
    ckpt = members[0] if members else None
    sc = scoring_of_logs(train_logs, 10) if ckpt is None else scoring_of_model(ckpt)
    rows: dict[str, dict[str, Any]] = {}
    for k in range(args.test_sets):
        real = versions_logs(args.test, 300 + 17 * k, tuple(CAR_TRAINED) + tuple(CAR_UNSEEN))
        if ckpt is None:  # the twin itself: fresh field runs stand in for the simulated ones
            sim = versions_logs(args.test * args.sims, 50_000 + 17 * k, tuple(CAR_TRAINED) + tuple(CAR_UNSEEN))
        else:
            sim = []
            for j, member in enumerate(members):
                engine = "native" if member.config.plain else "torch"  # models fed by the window alone run natively
                seed = k if len(members) == 1 else 1000 * k + j
                sim += simulate_versions(member, real, runs=args.sims, seed=seed, engine=engine)
        for g in verify(real, sim, system, skip=sc.skip, seed=k):
            row = rows.setdefault(
                g.version,
                {"goals": g.goals, "ratio": [], "matched": [], "floor": [], "p": [], "div": [], "n_real": g.n_real},
            )
            row["ratio"].append((g.matched.w1 / g.floor.w1).tolist())
            row["matched"].append(g.matched.w1.tolist())
            row["floor"].append(g.floor.w1.tolist())
            row["p"].append(g.tests["goals_w1"]["p_value"])
            mine = [lg for lg in sim if system.version_label(lg.controller) == g.version]
            theirs = [lg for lg in real if system.version_label(lg.controller) == g.version]
            row["div"].append(divergence(theirs, mine, sc))
    trained_labels = {system.version_label(lg.controller) for lg in train_logs}
    out = []
    for version, row in rows.items():
        ratio = np.asarray(row["ratio"])
        div = {key: sum(d[key] for d in row["div"]) for key in row["div"][0]}
        held = stats.fisher_exact(
            [
                [div["sim_held"], div["sim_runs"] - div["sim_held"]],
                [div["real_held"], div["real_runs"] - div["real_held"]],
            ],
            alternative="greater",
        )
        out.append(
            {
                "version": version,
                "role": "TMVK" if version in trained_labels else "TMVU",
                "goals": row["goals"],
                "ratio_mean": ratio.mean(axis=0).tolist(),
                "ratio_min": ratio.min(axis=0).tolist(),
                "ratio_max": ratio.max(axis=0).tolist(),
                "ratio_per_set": ratio.tolist(),
                "ratio_pooled": (np.sum(row["matched"], axis=0) / np.sum(row["floor"], axis=0)).tolist(),
                "ratio_pooled_ci95": pooled_interval(row["matched"], row["floor"]),
                "matched_w1_per_set": row["matched"],
                "floor_w1_per_set": row["floor"],
                "p_values": row["p"],
                "divergence": div,
                "sim_diverged": div["sim_held"] / div["sim_runs"],
                "real_diverged": div["real_held"] / div["real_runs"],
                "held_more_p": float(held.pvalue),
                "n_real_per_set": row["n_real"],
            }
        )
    worst = max(max(r["ratio_mean"]) for r in out)
    pooled = np.asarray([r["ratio_pooled"] for r in out])
    runaway = sum(r["divergence"]["sim_runaway"] for r in out)
    return {
        "config": name,
        "algorithm": algorithm,
        "train_kwargs": {
            "epochs": args.epochs,
            **{k: v.to_json() if isinstance(v, SelectionSettings) else v for k, v in extra.items()},
        },
        "train_seconds": round(train_s, 1),
        "selected_epoch": None if ckpt is None else (ckpt.record.selection or {}).get("best_epoch"),
        "versions": out,
        "worst_ratio": worst,
        "cells_above": int(sum(np.sum(np.asarray(r["ratio_mean"]) > TARGET) for r in out)),
        "worst_pooled": float(pooled.max()),
        "cells_above_pooled": int(np.sum(pooled > TARGET)),
        "sim_runaway": runaway,
        "meets_target": bool(worst <= TARGET and runaway == 0 and min(r["held_more_p"] for r in out) >= 0.05),
    }


def print_table(res: dict[str, Any]) -> None:
    goals = res["versions"][0]["goals"]
    print(
        f"\n== {res['config']} ({res['algorithm']} {res['train_kwargs']}, {res['train_seconds']} s, "
        f"epoch {res['selected_epoch']})"
    )
    head = " | ".join(f"{g[:16]:>16}" for g in goals)
    print(f"{'version':<26} {'role':<5} | {head} | {'p (per set)':<16} | held sim/real (p) | runaway sim/real")
    for r in res["versions"]:
        cells = " | ".join(
            f"{m:>5.2f} [{lo:.2f},{hi:.2f}]".rjust(16)
            for m, lo, hi in zip(r["ratio_mean"], r["ratio_min"], r["ratio_max"])
        )
        ps = ",".join(f"{p:.2f}" for p in r["p_values"])
        d = r["divergence"]
        print(
            f"{r['version']:<26} {r['role']:<5} | {cells} | {ps:<16} | "
            f"{r['sim_diverged']:.3f}/{r['real_diverged']:.3f} ({r['held_more_p']:.2f}) | "
            f"{d['sim_runaway']}/{d['sim_runs']} {d['real_runaway']}/{d['real_runs']}"
        )
    print("pooled ratio over the sets (sum of matched W1 / sum of floor W1) [95 % bootstrap over sets]:")
    for r in res["versions"]:
        ci = r["ratio_pooled_ci95"] or [[float("nan")] * 2] * len(goals)
        cells = " | ".join(f"{m:>5.2f} [{lo:.2f},{hi:.2f}]".rjust(16) for m, (lo, hi) in zip(r["ratio_pooled"], ci))
        print(f"{r['version']:<26} {r['role']:<5} | {cells}")
    verdict = "MET" if res["meets_target"] else "NOT met"
    print(
        f"worst goal ratio {res['worst_ratio']:.2f} (target <= {TARGET}), {res['cells_above']} cells above, "
        f"{res['sim_runaway']} simulated runs run away: {verdict}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default="default", help=f"comma-separated, of: {', '.join(CONFIGS)}")
    ap.add_argument("--n", type=int, default=20, help="training logs per trained version")
    ap.add_argument("--test", type=int, default=20, help="test logs per version and test set")
    ap.add_argument("--test-sets", type=int, default=2)
    ap.add_argument("--sims", type=int, default=2, help="simulated runs per test log")
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--train-seed",
        type=int,
        default=100,
        help="the twin's seed for the training logs (a diagnostic; 100 by default)",
    )
    ap.add_argument("--quick", action="store_true", help="a smoke run: 30 epochs, 10 logs, 1 test set")
    ap.add_argument("--save-dir", type=Path, default=None, help="keep each config's model there as <config>.pt")
    ap.add_argument("--load-dir", type=Path, default=None, help="use <config>.pt from there instead of training")
    ap.add_argument(
        "--mixture",
        type=Path,
        nargs="+",
        default=None,
        metavar="DIR",
        help="a run-level ensemble: <config>.pt from every DIR (e.g. --save-dir folders of several --seed), "
        "each simulating --sims runs from every test log",
    )
    ap.add_argument("--out", type=Path, default=Path("bench_out/fidelity_car.json"))
    args = ap.parse_args()
    if args.mixture and args.load_dir:
        sys.exit("fidelity_car: --mixture and --load-dir exclude each other")
    missing = [str(d / f"{c}.pt") for d in args.mixture or [] for c in args.configs.split(",") if c != TWIN]
    missing = [m for m in missing if not Path(m).is_file()]
    if missing:
        sys.exit(f"fidelity_car: --mixture: no model {missing[0]}")
    if args.quick:
        args.epochs, args.n, args.test, args.test_sets = 30, 10, 10, 1
    torch.set_num_threads(1)
    results = []
    for name in args.configs.split(","):
        if name not in CONFIGS:
            sys.exit(f"fidelity_car: unknown config {name!r}; known: {', '.join(CONFIGS)}")
        results.append(run_config(name, args))
        print_table(results[-1])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "torch": torch.__version__,
        "argv": sys.argv[1:],
        "n_train_per_version": args.n,
        "test_per_version": args.test,
        "test_sets": args.test_sets,
        "sims_per_test_log": args.sims,
    }
    args.out.write_text(json.dumps({"meta": meta, "results": results}, indent=1))
    print(f"\nwritten {args.out}")


if __name__ == "__main__":
    main()

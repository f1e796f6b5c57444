"""The main job on the project's own data: the twin plays the field.

Twin logs of five controller versions are written like field logs; a model is trained on three of
them (TMVK), selected on held-out logs of those, simulated from the initial windows of held-out
logs of all five versions (the two never trained on are TMVU), and verified against them. The
lane-keeping robot (x = 10..50, trained on 10, 30, 50) and the car following a lead vehicle (five
gain sets, trained on three) are the two shipped systems. Simulation takes the native engine
whenever it can run the model (``engine="auto"``), as ``envi simulate`` does.

The output folder is the demo's own (``demo_out`` by default, written on every ``./dev.sh demo``):
a run replaces the logs an earlier demo left in its ``data/`` and ``sim/`` subfolders instead of
refusing as ``envi simulate`` does, since a second demo is the normal case and the logs it reads
back must be this run's only (a ``--fast`` demo after a full one would read 14 stale logs per
version, a lane-keeping demo after a car one two schemas). Other files there stay.
"""

from __future__ import annotations

import os

from dataclasses import dataclass
from pathlib import Path

from .controllers import ControllerSpec
from .logs import Log, group_by_controller, load_logs, remove_logs, write_log
from .simulate import choose_engine, simulate_versions
from .system import load_system
from .train import train
from .verify import to_text, verify, write_report


@dataclass(frozen=True)
class DemoSize:
    """Logs per version and training budget: the full demo and ``--fast``.

    The logs a version keeps for verification are its ``runs_per_version - n_train - n_val``: the
    report's real-vs-real floor compares two halves of them, and halves of 5 runs (the demo's until
    2026-11) gave KLD floors from 1.8 to 68 for the same twin, lenient enough to call almost any
    model "within". Halves of 15 runs cost the twin nothing to generate and the native engine a few
    seconds to simulate."""

    runs_per_version: int = 50
    n_train: int = 15
    n_val: int = 5
    epochs: int = 300
    sim_runs: int = 10


FULL, FAST = DemoSize(), DemoSize(runs_per_version=24, n_train=8, n_val=3, epochs=40, sim_runs=4)


def _lane_logs(data: Path, runs: int, seed: int) -> tuple[list[Log], set[ControllerSpec]]:
    from .twin import generate, write_logs

    for x in (10, 20, 30, 40, 50):
        write_logs(generate(ControllerSpec("lane-keeping", {"x": x}), runs, 100, seed=seed + x), data)
    return load_logs(data, min_length=11), {ControllerSpec("lane-keeping", {"x": x}) for x in (10, 30, 50)}


def _car_logs(data: Path, runs: int, seed: int) -> tuple[list[Log], set[ControllerSpec]]:
    from .twin.car import CAR_TRAINED, car_versions, generate_car_versions, write_car_logs

    write_car_logs(generate_car_versions(runs, 100, seed=seed), data)
    specs = car_versions()
    return load_logs(data, load_system("car"), min_length=11), {specs[i] for i in CAR_TRAINED}


def run_demo(
    out: Path, seed: int = 0, system: str = "lane-keeping", size: DemoSize = FULL, epochs: int | None = None
) -> Path:
    """Generate, train, simulate, verify; returns the report's Markdown path. The logs an earlier
    demo left in ``out/data`` and ``out/sim`` are replaced (see the module's docstring)."""
    if system not in ("lane-keeping", "car"):
        raise ValueError(f"no demo for system {system!r}; choose lane-keeping or car")
    data, sim_dir = out / "data", out / "sim"
    replaced = remove_logs(data) + remove_logs(sim_dir)
    if replaced:
        print(f"replaced {replaced} logs of an earlier demo in {data} and {sim_dir}")
    if system == "lane-keeping":
        logs, trained = _lane_logs(data, size.runs_per_version, seed)
    else:
        logs, trained = _car_logs(data, size.runs_per_version, seed)
    train_logs, val_logs, test_logs = [], [], []
    for spec, group in group_by_controller(logs).items():
        if spec in trained:
            train_logs += group[: size.n_train]
            val_logs += group[size.n_train : size.n_train + size.n_val]
        test_logs += group[size.n_train + size.n_val :]
    desc = load_system(system)
    print(
        f"twin data ({system}): {len(logs)} logs in {data}; training on {len(train_logs)} logs of "
        f"{len(trained)} versions, validating on {len(val_logs)}, verifying on {len(test_logs)} "
        f"(all {len(group_by_controller(logs))} versions, the untrained ones are TMVU)"
    )
    epochs = size.epochs if epochs is None else epochs
    ckpt = train(
        "bc", train_logs, val_logs, system=desc, seed=seed, epochs=epochs, progress=True, jobs=os.cpu_count() or 1
    )
    ckpt.save(out / "model.pt")
    engine = choose_engine(ckpt, next(iter(group_by_controller(test_logs))), "auto")
    sims = simulate_versions(ckpt, test_logs, runs=size.sim_runs, seed=seed, engine="auto")
    for i, lg in enumerate(sims):
        write_log(lg, sim_dir / f"{i:05d}_{lg.meta.run_id}.csv")
    print(f"simulated {len(sims)} runs on the {engine} engine")
    results = verify(test_logs, sims, desc, skip=ckpt.config.history, seed=seed)
    print(to_text(results))
    md, _ = write_report(
        results,
        out / "report",
        f"Demo ({system}): BC model of the twin, trained on {len(trained)} versions, verified on all (TMVK and TMVU)",
        real=test_logs,
        sim=sims,
        system=desc,
        skip=ckpt.config.history,
        model=out / "model.pt",
    )
    print(f"report: {md.with_suffix('.html')} {md}")
    return md

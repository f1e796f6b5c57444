"""The Python API: the command line's steps as functions, for a notebook.

``from envi_py import api as envi`` gives them. (Not ``import envi_py as envi``: the package's own
modules are named ``train``, ``simulate``, ``verify``, ``check``, ``diagnose``, and importing one
binds its name on the package, so a function of that name there would be replaced by the module.)::

    logs = envi.load("logs/", system="car")
    model = envi.train(logs[:40], logs[40:50])
    sims = envi.simulate(model, logs[50:], runs=5)
    report = envi.verify(logs[50:], sims)
    report.to_dataframe()          # one row per version and goal
    verdicts = envi.check(model, logs[50:])
    verdicts.to_dataframe()        # one row per version and requirement
    envi.diagnose(model, logs[50:], retrain=False).verdict()

Every function is a thin layer over the module the command line uses (one owner per concept):
:func:`envi_py.logs.load_logs`, :func:`envi_py.train.train`, :func:`envi_py.simulate.simulate_versions`,
:func:`envi_py.verify.verify`, :func:`envi_py.check.check`, :func:`envi_py.diagnose.run.diagnose`.
Results keep the full objects (``.groups``, ``.rows``) beside their tables.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .logs import Log, load_logs
from .model import Checkpoint
from .system import SystemDescription, load_system


def _system(system: str | os.PathLike | SystemDescription | None, pattern: str | None) -> SystemDescription | None:
    sd = load_system(system) if isinstance(system, (str, os.PathLike)) else system
    if pattern is not None:
        sd = (sd or load_system("lane-keeping")).with_pattern(pattern)
    return sd


def load(
    sources: str | os.PathLike | Sequence[str | os.PathLike],
    system: str | os.PathLike | SystemDescription | None = None,
    pattern: str | None = None,
    where: dict[str, Any] | None = None,
) -> list[Log]:
    """Logs from files, folders or manifests; ``system`` a shipped name (``"car"``), a TOML file or a
    description; ``pattern`` reads version parameters from file names (``"log_{x}_{run}.csv"``)."""
    return load_logs(sources, _system(system, pattern), where=where)


def train(logs: Sequence[Log], val_logs: Sequence[Log] = (), algorithm: str = "bc", **options: Any) -> Checkpoint:
    """A model of the logs' environment (``envi train``); ``options`` as the trainer's keywords
    (``epochs``, ``lr``, ``head``, ``history``, ``seed``...)."""
    from .train import train as run

    return run(algorithm, logs, val_logs, **options)


def model(path: str | os.PathLike) -> Checkpoint:
    """A saved model (``envi train -o``)."""
    return Checkpoint.load(path)


def simulate(
    ckpt: Checkpoint | str | os.PathLike, init_logs: Sequence[Log], runs: int = 1, seed: int = 0, engine: str = "auto"
) -> list[Log]:
    """``runs`` simulated runs from each log's sigma_0 under its own controller version (``envi simulate``)."""
    from .simulate import simulate_versions

    ck = ckpt if isinstance(ckpt, Checkpoint) else Checkpoint.load(ckpt)
    return simulate_versions(ck, init_logs, runs=runs, seed=seed, engine=engine)


@dataclass
class Verification:
    """``envi verify``'s result: per version and goal, real vs simulated at matched sizes."""

    groups: list[Any]  # envi_py.verify.GroupResult

    def records(self) -> list[dict[str, Any]]:
        """One plain row per version and goal."""
        out = []
        for g in self.groups:
            for j, goal in enumerate(g.goals):
                out.append(
                    {
                        "version": g.version,
                        "goal": goal,
                        "real_runs": g.n_real,
                        "sim_runs": g.n_sim,
                        "real_mean": float(g.real_mean[j]),
                        "sim_mean": float(g.sim_mean[j]),
                        "w1_matched": None if g.matched is None else float(g.matched.w1[j]),
                        "w1_floor": None if g.floor is None else float(g.floor.w1[j]),
                        "test_p": (g.tests.get("goals_w1") or {}).get("p_value"),
                        "within_floor": g.within_floor,
                    }
                )
        return out

    def to_dataframe(self) -> Any:
        return _frame(self.records())

    def to_markdown(self) -> str:
        from .verify import to_markdown

        return to_markdown(self.groups)

    def write(
        self,
        out: str | os.PathLike,
        real: Sequence[Log] = (),
        sim: Sequence[Log] = (),
        system: SystemDescription | None = None,
    ) -> Path:
        """``envi verify``'s report files in ``out``; with the logs also the trace overlays (fit per
        state) and every version's metric distributions. Returns the HTML page to open."""
        from .verify import write_report

        md, _ = write_report(self.groups, Path(out), real=real, sim=sim, system=system)
        return md.with_suffix(".html")

    def plot(self, ax: Any = None) -> Any:
        """Matched W1 beside the real-vs-real floor, per version and goal (a matplotlib Axes)."""
        import matplotlib.pyplot as plt

        rows = [r for r in self.records() if r["w1_floor"] is not None]
        if ax is None:
            _, ax = plt.subplots(figsize=(max(4.0, 0.6 * len(rows)), 3.5))
        labels = [f"{r['version']}\n{r['goal']}" for r in rows]
        xs = range(len(rows))
        ax.bar([x - 0.2 for x in xs], [r["w1_matched"] for r in rows], 0.4, label="sim vs real (matched)")
        ax.bar([x + 0.2 for x in xs], [r["w1_floor"] for r in rows], 0.4, label="real vs real (floor)")
        ax.set_xticks(list(xs), labels, rotation=60, ha="right", fontsize=7)
        ax.set_ylabel("W1 / goal scale")
        ax.legend(fontsize=7)
        return ax


def verify(real: Sequence[Log], sim: Sequence[Log], system: SystemDescription | None = None) -> Verification:
    """Real vs simulated runs per version and goal, with the fair floor (``envi verify``)."""
    from .verify import verify as run

    return Verification(run(real, sim, system))


@dataclass
class Verdicts:
    """``envi check``'s result: per version and requirement, the verdicts and what they rest on."""

    rows: list[Any]  # envi_py.check.CheckRow

    def records(self) -> list[dict[str, Any]]:
        return [
            {
                "version": r.version,
                "requirement": r.requirement,
                "p_required": r.p_required,
                "real_runs": r.n_real,
                "sim_verdict": r.simulation.get("verdict"),
                "sim_runs": r.simulation.get("runs"),
                "real_verdict": r.real_system.get("verdict"),
                "basis": r.real_system.get("basis"),
                "low": (r.real_system.get("interval") or [None, None])[0],
                "high": (r.real_system.get("interval") or [None, None])[1],
            }
            for r in self.rows
        ]

    def to_dataframe(self) -> Any:
        return _frame(self.records())

    def write(self, out: str | os.PathLike, settings: dict[str, Any] | None = None) -> Path:
        """``envi check``'s report files in ``out`` (``settings``: alpha, delta, ... as listed in the
        provenance); returns the HTML page to open."""
        from .check import write_check

        meta = {"alpha": 0.05, "delta": 0.05, "max_runs": 4000, **(settings or {})}
        md, _ = write_check(self.rows, Path(out), meta)
        return md.with_suffix(".html")


def check(
    ckpt: Checkpoint | str | os.PathLike,
    real: Sequence[Log],
    require: Sequence[str] = (),
    probability: float | None = None,
    unseen: Sequence[Any] = (),
    **options: Any,
) -> Verdicts:
    """PASS / FAIL / UNDECIDED per version and requirement (``envi check``); ``require`` as on the
    command line (``"min(distance) >= 10@0.95"``), else the system description's requirements;
    ``probability`` for the required ones without '@' (default 0.9)."""
    from .check import check as run
    from .check import requirements_of

    ck = ckpt if isinstance(ckpt, Checkpoint) else Checkpoint.load(ckpt)
    return Verdicts(run(ck, real, requirements_of(ck.system, list(require), probability), unseen, **options))


def diagnose(
    ckpt: Checkpoint | str | os.PathLike, real: Sequence[Log], confirm: Sequence[Log] | None = None, **options: Any
) -> Any:
    """Where simulation and reality differ, which unmodelled effect explains it and how far adding it
    shrinks the gap (``envi diagnose``); ``.verdict()`` is the paragraph to read first."""
    from .diagnose.run import diagnose as run

    ck = ckpt if isinstance(ckpt, Checkpoint) else Checkpoint.load(ckpt)
    return run(ck, real, confirm, **options)


def _frame(records: list[dict[str, Any]]) -> Any:
    try:
        import pandas as pd
    except ImportError:
        raise ImportError("to_dataframe needs pandas: pip install 'envi[notebook]' (or pandas)") from None
    return pd.DataFrame.from_records(records)


__all__ = ["load", "train", "model", "simulate", "verify", "check", "diagnose", "Verification", "Verdicts"]

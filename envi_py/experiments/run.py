"""Run a grid: build the jobs, send them to an executor, write the report. Same seed, same numbers:
every job is seeded from (seed, repetition, n) and results are ordered by job, not by finish time."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Sequence

from tqdm import tqdm

from ..logs import Log
from .executor import Executor, LocalExecutor
from .grid import ALGORITHMS, make_jobs
from .report import write_report
from .worker import run_job


def run_experiment(logs: Sequence[Log], use_cases: Sequence[str], out: str | Path, *,
                   algorithms: Sequence[str] = ALGORITHMS, ns: Sequence[int] = (3, 15, 30), reps: int = 5,
                   seed: int = 0, protocol: str = "random", epochs: int = 300, n_val: int = 3, n_test: int = 30,
                   runs: int = 1, executor: Executor | None = None, progress: bool = True,
                   train_kwargs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train and verify every job of the grid; returns the metadata and writes ``out``."""
    kwargs = {"epochs": epochs, **(train_kwargs or {})}
    jobs = make_jobs(logs, use_cases, algorithms, ns, reps, seed, protocol, n_val, n_test, kwargs, runs)
    own = executor is None
    executor = executor or LocalExecutor()
    results: list[Any] = [None] * len(jobs)
    t0 = time.perf_counter()
    try:
        for i, res in tqdm(executor.map(run_job, jobs), total=len(jobs), desc="experiment", disable=not progress):
            results[i] = res
    finally:
        if own:
            executor.close()
    meta = {"use_cases": list(use_cases), "algorithms": list(algorithms), "ns": list(ns), "reps": reps,
            "seed": seed, "protocol": protocol, "epochs": epochs, "n_val": n_val, "n_test": n_test, "runs": runs,
            "train_kwargs": kwargs, "jobs": len(jobs), "wall_seconds": time.perf_counter() - t0}
    report = write_report(results, meta, Path(out))
    return {"meta": meta, "report": str(report), "results": results}

"""Run a grid: build the jobs, send them to an executor, write the report. Same seed, same numbers:
every job is seeded from (seed, repetition, n) and results are ordered by job, not by finish time."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..goals.presets import LANE_KEEPING_BAND, lane_keeping_centre
from ..logs import Log
from ..system import SystemDescription, describe_schema
from .executor import Executor, LocalExecutor
from .grid import ALGORITHMS, make_jobs
from .report import write_report
from .versions import VersionChoice
from .worker import run_job


def _read_journal(path: Path) -> dict[str, Any]:
    """Finished jobs of an earlier run by fingerprint; a torn last line (killed mid-write) is ignored."""
    done: dict[str, Any] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            done[rec["fingerprint"]] = rec["result"]
    return done


def run_experiment(
    logs: Sequence[Log],
    use_cases: Sequence[str],
    out: str | Path,
    *,
    algorithms: Sequence[str] = ALGORITHMS,
    ns: Sequence[int] = (3, 15, 30),
    reps: int = 5,
    seed: int = 0,
    protocol: str = "random",
    epochs: int = 300,
    n_val: int = 3,
    n_test: int = 30,
    runs: int = 1,
    executor: Executor | None = None,
    progress: bool = True,
    train_kwargs: dict[str, Any] | None = None,
    resume: bool = True,
    system: SystemDescription | None = None,
    versions: VersionChoice | None = None,
) -> dict[str, Any]:
    """Train and verify every job of the grid; returns the metadata and writes ``out``.

    ``system``: the logs' description (default: the one of their schema), which names the versions
    and the goals; ``versions``: which versions train and which are verified (see
    :func:`.versions.plan_versions`; the paper's for the lane-keeping x logs).

    Each finished job is appended to ``out/jobs.jsonl`` at once; with ``resume`` a re-run reuses the
    jobs whose fingerprint (logs, seed, settings) matches, so an interrupted grid continues where it
    stopped and a grown grid (more repetitions, another n) only trains what is new.
    """
    kwargs = {"epochs": epochs, **(train_kwargs or {})}
    if not logs:
        raise ValueError("no logs to experiment on")
    system = system or describe_schema(logs[0].meta.schema)
    jobs, plan = make_jobs(
        logs, use_cases, algorithms, ns, reps, seed, protocol, n_val, n_test, kwargs, runs, system, versions
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    journal = out / "jobs.jsonl"
    done = _read_journal(journal) if resume else {}
    prints = [job.fingerprint() for job in jobs]
    results: list[Any] = [done.get(fp) for fp in prints]
    todo = [i for i, r in enumerate(results) if r is None]
    own = executor is None
    executor = executor or LocalExecutor()
    t0 = time.perf_counter()
    try:
        with journal.open("a" if resume else "w") as jf:
            for j, res in tqdm(
                executor.map(run_job, [jobs[i] for i in todo]), total=len(todo), desc="experiment", disable=not progress
            ):
                results[todo[j]] = res
                jf.write(json.dumps({"fingerprint": prints[todo[j]], "result": res}) + "\n")
                jf.flush()
    finally:
        if own:
            executor.close()
    meta = {
        "use_cases": list(use_cases),
        "algorithms": list(algorithms),
        "ns": list(ns),
        "reps": reps,
        "seed": seed,
        "protocol": protocol,
        "epochs": epochs,
        "n_val": n_val,
        "n_test": n_test,
        "runs": runs,
        "train_kwargs": kwargs,
        "jobs": len(jobs),
        "jobs_reused": len(jobs) - len(todo),
        "wall_seconds": time.perf_counter() - t0,
        "system": system.name,
        "units": {c.name: c.unit for c in system.schema.channels},
        "versions": plan.to_json(),
        "state_ranges": {
            c.name: [c.low, c.high] if math.isfinite(c.low) and math.isfinite(c.high) else None
            for c in system.schema.states
        },
    }
    if system.preset == "lane-keeping":
        centre = lane_keeping_centre(system)
        meta["lane_band"] = [centre - LANE_KEEPING_BAND, centre + LANE_KEEPING_BAND]
    report = write_report(results, meta, Path(out))
    return {"meta": meta, "report": str(report), "results": results}

"""Run a grid: build the jobs, send them to an executor, write the report. Same seed, same numbers:
every job is seeded from (seed, repetition, n) and results are ordered by job, not by finish time."""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..files import read_text
from ..goals.presets import LANE_KEEPING_BAND, lane_keeping_centre
from ..logs import Log
from ..notes import note
from ..system import SystemDescription, describe_schema
from ..executor import Executor, LocalExecutor
from .grid import ALGORITHMS, Job, make_jobs
from .report import write_report
from .versions import VersionChoice
from .worker import run_job


def _digest(result: Any) -> str:
    return hashlib.sha256(json.dumps(result, sort_keys=True).encode()).hexdigest()


def _journal_line(fingerprint: str, result: Any) -> str:
    """One finished job, with the digest of its result: a record edited or damaged later is known."""
    return json.dumps({"fingerprint": fingerprint, "result": result, "sha256": _digest(result)}) + "\n"


def _read_journal(path: Path) -> dict[str, Any]:
    """Finished jobs of an earlier run by fingerprint. A record that does not parse, lacks its parts
    or whose result no longer matches its digest is not reused (its job runs again) and one line on
    stderr says which lines; a torn last line (killed mid-write) is dropped without a word."""
    done: dict[str, Any] = {}
    if not path.exists():
        return done
    lines = read_text(path, "an experiment journal").splitlines()
    damaged = []
    for i, line in enumerate(lines, 1):
        try:
            rec = json.loads(line)
            ok = isinstance(rec, dict) and isinstance(rec.get("fingerprint"), str) and "result" in rec
            ok = ok and rec.get("sha256") == _digest(rec["result"])
        except json.JSONDecodeError:
            ok = False
        if ok:
            done[rec["fingerprint"]] = rec["result"]
        elif i < len(lines) or line.strip().startswith("{") and line.strip().endswith("}"):
            damaged.append(i)
    if damaged:
        shown = ", ".join(map(str, damaged[:5])) + (", ..." if len(damaged) > 5 else "")
        what = f"{len(damaged)} damaged or unverifiable record(s) (line {shown})"
        note(f"envi experiment: note: {path}: {what} not reused; their jobs run again")
    return done


def jobs_summary(todo: Sequence[Job], reused: int) -> str:
    """One line on what is about to run: trainings per algorithm, and what is reused from the journal.
    The progress bar's estimate follows the first jobs done, which may be the fast ones."""
    per = Counter(job.algorithm for job in todo)
    slow = [a for a in ("gail", "bcxgail") if a in per]
    return (
        f"envi experiment: {len(todo)} training(s) to run ({', '.join(f'{n} {a}' for a, n in per.items())})"
        + (f", {reused} reused from the journal" if reused else "")
        + (f"; {' and '.join(slow)} take minutes each, the bar's first estimate does not know it" if slow else "")
    )


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
    if progress and todo:  # say the size before the first training, not as a bar that starts with the fast ones
        print(jobs_summary([jobs[i] for i in todo], len(jobs) - len(todo)), file=sys.stderr)
    own = executor is None
    executor = executor or LocalExecutor()
    t0 = time.perf_counter()
    try:
        # a fresh run journals beside the old journal and replaces it only when complete: an
        # interrupted --fresh keeps every job the earlier run had finished
        writing = journal if resume else journal.with_name(journal.name + ".fresh")
        with writing.open("a" if resume else "w") as jf:
            if resume and jf.tell() and not journal.read_bytes().endswith(b"\n"):
                jf.write("\n")  # after a torn last line: the next record starts a line of its own
            for j, res in tqdm(
                executor.map(run_job, [jobs[i] for i in todo]), total=len(todo), desc="experiment", disable=not progress
            ):
                results[todo[j]] = res
                jf.write(_journal_line(prints[todo[j]], res))
                jf.flush()
        if writing != journal:
            os.replace(writing, journal)
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

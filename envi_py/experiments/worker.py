"""One job of the grid, run in a worker process (local pool or Dask): train, simulate, verify.

Returns plain numbers and names only, so results travel back cheaply and the report never needs
the models. Torch is limited to one thread per worker: the grid's parallelism is across jobs.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..controllers import ControllerSpec
from ..logs import Log
from ..verify import verify
from .grid import Job
from .versions import version_label

TRACES_KEPT = 3  # real and simulated traces kept per controller version for the trace plots


def geometric_mean_kld(klds: list[float | None]) -> float | None:
    """The authors' summary of KLDs: exp(mean(log KLD)), robust to one exploding version; None
    unless every version has a finite KLD (only the lane-keeping preset defines one)."""
    if not klds or any(k is None or not math.isfinite(k) for k in klds):
        return None
    return float(np.exp(np.mean(np.log(np.maximum(klds, 1e-12)))))


def state_traces(logs: list[Log]) -> dict[str, list[list[float]]]:
    """Every state channel of ``logs`` by name, one list per log (for the trace plots)."""
    if not logs:
        return {}
    names = [c.name for c in logs[0].meta.schema.states]
    return {name: [lg.states[:, j].tolist() for lg in logs] for j, name in enumerate(names)}


def trainer_kwargs(algorithm: str, kwargs: dict[str, Any]) -> dict[str, Any]:
    """The grid's training keywords an algorithm accepts: GAIL's own hyper-parameters (horizon,
    discriminator size...) go to gail and bcxgail only; shared ones (epochs, lr, hidden...) to all."""
    from dataclasses import fields

    from ..train.gail import GailConfig

    if algorithm in ("gail", "bcxgail"):
        return dict(kwargs)
    gail_only = {f.name for f in fields(GailConfig)} - {"lr", "eval_every"}
    return {k: v for k, v in kwargs.items() if k not in gail_only}


def run_job(job: Job) -> dict[str, Any]:
    import torch

    from ..simulate import simulate_versions
    from ..train import train

    torch.set_num_threads(1)
    skip = job.train_kwargs.get("history", 10)
    t0 = time.perf_counter()
    ckpt = train(
        job.algorithm,
        job.train,
        job.val,
        system=job.system,
        seed=job.seed,
        **trainer_kwargs(job.algorithm, job.train_kwargs),
    )
    seconds = time.perf_counter() - t0
    evals: dict[str, Any] = {}
    for uc, logs in job.evals.items():
        sims = simulate_versions(ckpt, logs, runs=job.runs, seed=job.seed)
        groups = []
        for r in verify(logs, sims, job.system, skip=skip, seed=0):
            spec = ControllerSpec.from_json(r.controller)
            real_v = [lg for lg in logs if lg.controller == spec][:TRACES_KEPT]
            sim_v = [s for s in sims if s.controller == spec][: TRACES_KEPT * job.runs : job.runs]
            g = r.to_json()
            g["version"] = version_label(spec, job.system)
            g["traces"] = {"real": state_traces(real_v), "sim": state_traces(sim_v)}
            groups.append(g)
        order = job.versions.get(uc, [])
        groups.sort(key=lambda g: order.index(g["version"]) if g["version"] in order else len(order))
        evals[uc] = {
            "groups": groups,
            "goals": groups[0]["goals"] if groups else [],
            "kld_geomean": geometric_mean_kld([g["sim_vs_real"]["kld"] for g in groups]),
            "test_logs": [lg.name for lg in logs],
        }
    return {
        "family": job.family,
        "algorithm": job.algorithm,
        "n": job.n,
        "rep": job.rep,
        "seed": job.seed,
        "versions": job.versions,
        "train_logs": [lg.name for lg in job.train],
        "val_logs": [lg.name for lg in job.val],
        "train_seconds": seconds,
        "selection": {k: v for k, v in ckpt.record.selection.items() if k != "curve"},
        "evals": evals,
    }

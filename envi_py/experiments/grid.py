"""The experiment grid: which logs train, validate and test each model, for the paper's use cases.

Paper, Section 6: TOVK trains and verifies one version; TMVK trains on several and verifies each of
them; TMVU verifies unseen versions with the TMVK models (:mod:`.versions` says which, for any
system). TMVK and TMVU therefore share their trainings: a job is one training (use-case family,
algorithm, n, repetition) evaluated on every requested evaluation set.

Two protocols choose the logs:

``random`` (ours): per repetition r, each version's logs are shuffled with seed (seed, r, version);
the last ``n_test`` are that version's test logs, the ``n_val`` before them its validation logs,
and the first n of the rest its training logs. The test logs are therefore the same for every n
and every algorithm of a repetition and never overlap training or validation logs.

``authors``: the authors' published split, reproduced: files in sorted order, 5 folds; fold f
rotates each version's list by f * len / 5; the first n of the rotated list train, the last 10
test; no validation logs (they kept the last epoch).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..logs import Log
from ..system import SystemDescription, describe_schema
from .versions import Plan, Version, VersionChoice, plan_versions, versions_of

FAMILY = {"tovk": "tovk", "tmvk": "tmv", "tmvu": "tmv"}  # use cases sharing a family share trainings
ALGORITHMS = ("random", "bc", "gail", "bcxgail")


@dataclass
class Job:
    """One training and its evaluations; everything a worker needs, logs included (picklable)."""

    family: str
    algorithm: str
    n: int
    rep: int
    seed: int
    train: list[Log]
    val: list[Log]
    evals: dict[str, list[Log]]  # use case -> test logs
    system: SystemDescription
    versions: dict[str, list[str]]  # "train" and each use case -> version labels
    train_kwargs: dict[str, Any] = field(default_factory=dict)
    runs: int = 1

    @property
    def key(self) -> tuple[str, str, int, int]:
        return (self.family, self.algorithm, self.n, self.rep)

    def fingerprint(self) -> str:
        """Everything that determines the job's result; a finished job with the same one is reused."""
        blob = json.dumps(
            {
                "key": self.key,
                "seed": self.seed,
                "train": [lg.sha256() for lg in self.train],
                "val": [lg.sha256() for lg in self.val],
                "evals": {k: [lg.sha256() for lg in v] for k, v in sorted(self.evals.items())},
                "kwargs": self.train_kwargs,
                "runs": self.runs,
                "versions": self.versions,
                "system": self.system.to_json(),
            },
            sort_keys=True,
            default=str,
        )
        return hashlib.sha256(blob.encode()).hexdigest()


def _split_random(
    pool: dict[str, Version], labels: Sequence[str], n: int, rep: int, seed: int, n_val: int, n_test: int, max_n: int
) -> tuple[list[Log], list[Log], dict[str, list[Log]]]:
    train, val, test = [], [], {}
    for x in labels:
        logs = pool[x].logs
        perm = np.random.default_rng([seed, rep, *pool[x].entropy()]).permutation(len(logs))
        k_test = min(n_test, len(logs) - max_n - n_val)
        if k_test < 2:
            raise ValueError(f"{x}: {len(logs)} logs cannot hold {max_n} training, {n_val} validation and 2 test logs")
        test[x] = [logs[i] for i in sorted(perm[len(logs) - k_test :])]
        val += [logs[i] for i in sorted(perm[len(logs) - k_test - n_val : len(logs) - k_test])]
        train += [logs[i] for i in sorted(perm[:n])]
    return train, val, test


def _split_authors(
    pool: dict[str, Version], labels: Sequence[str], n: int, fold: int, folds: int = 5, n_test: int = 10
) -> tuple[list[Log], list[Log], dict[str, list[Log]]]:
    train, test = [], {}
    for x in labels:
        logs = sorted(pool[x].logs, key=lambda lg: lg.name)
        shift = fold * len(logs) // folds
        rotated = logs[shift:] + logs[:shift]
        if n + n_test > len(rotated):
            raise ValueError(f"{x}: {len(logs)} logs cannot hold {n} training and {n_test} test logs")
        train += rotated[:n]
        test[x] = rotated[-n_test:]
    return train, [], test


def make_jobs(
    logs: Sequence[Log],
    use_cases: Sequence[str],
    algorithms: Sequence[str] = ALGORITHMS,
    ns: Sequence[int] = (3, 15, 30),
    reps: int = 5,
    seed: int = 0,
    protocol: str = "random",
    n_val: int = 3,
    n_test: int = 30,
    train_kwargs: dict[str, Any] | None = None,
    runs: int = 1,
    system: SystemDescription | None = None,
    versions: VersionChoice | None = None,
) -> tuple[list[Job], Plan]:
    """Every (family, algorithm, n, repetition) training with its logs, in a fixed order, and the
    versions each use case trains on and verifies.

    ``system`` names the versions (default: the description of the logs' schema); ``versions`` is
    the user's choice of them (see :func:`.versions.plan_versions`). With the authors' protocol the
    repetitions are their folds (at most 5).
    """
    if not logs:
        raise ValueError("no logs to experiment on")
    system = system or describe_schema(logs[0].meta.schema)
    pool = versions_of(logs, system)
    plan = plan_versions(pool, use_cases, versions or VersionChoice())
    if protocol == "authors" and reps > 5:
        raise ValueError("the authors' protocol has 5 folds: --reps at most 5")
    families: dict[str, list[str]] = {}
    for uc in use_cases:
        families.setdefault(FAMILY[uc], []).append(uc)
    jobs = []
    max_n = max(ns)
    for rep in range(reps):  # repetition-major: an interrupted grid still holds whole repetitions
        for family, ucs in families.items():
            labels = plan.train[ucs[0]]
            chosen = {"train": list(labels)} | {uc: list(plan.eval[uc]) for uc in ucs}
            for n in ns:
                if protocol == "authors":
                    train, val, test = _split_authors(pool, labels, n, rep)
                else:
                    train, val, test = _split_random(pool, labels, n, rep, seed, n_val, n_test, max_n)
                evals = {}
                for uc in ucs:
                    if uc == "tmvu":  # unseen versions: no log of them is used for anything else
                        evals[uc] = [
                            lg
                            for x in plan.eval[uc]
                            for lg in (
                                pool[x].logs
                                if protocol == "random"
                                else sorted(pool[x].logs, key=lambda g: g.name)[-10:]
                            )
                        ]
                    else:
                        evals[uc] = [lg for x in plan.eval[uc] for lg in test[x]]
                for algo in algorithms:
                    jobs.append(
                        Job(
                            family,
                            algo,
                            n,
                            rep,
                            int(seed * 100003 + rep * 1009 + n),
                            train,
                            val,
                            evals,
                            system,
                            chosen,
                            dict(train_kwargs or {}),
                            runs,
                        )
                    )
    return jobs, plan

"""The experiment grid on a tiny setting: log splits, determinism, report files, the Dask path."""

from __future__ import annotations

import json

import pytest

from envi_py.experiments.grid import make_jobs
from envi_py.experiments.run import run_experiment
from envi_py.experiments.executor import DaskExecutor, LocalExecutor
from envi_py.experiments.grid import version_of

TINY = {"hidden": (8,), "eval_every": 2, "horizon": 10, "disc_hidden": (8,), "value_hidden": (8,)}


def _names(logs) -> set[str]:
    return {lg.name for lg in logs}


def test_random_splits_are_disjoint_and_shared_across_n(real_logs) -> None:
    jobs = make_jobs(real_logs, ["tovk", "tmvk", "tmvu"], ["bc"], ns=(3, 15), reps=2, seed=1)
    assert {j.family for j in jobs} == {"tovk", "tmv"} and len(jobs) == 2 * 2 * 2
    for j in jobs:
        train, val = _names(j.train), _names(j.val)
        assert not train & val
        for uc, test in j.evals.items():
            assert not _names(test) & (train | val), uc
        if j.family == "tmv":
            assert {version_of(lg) for lg in j.evals["tmvu"]} == {20.0, 40.0}
            assert {version_of(lg) for lg in j.train} == {10.0, 30.0, 50.0}
            assert len(j.train) == 3 * j.n
    tovk = [j for j in jobs if j.family == "tovk"]
    by_rep = {}
    for j in tovk:  # the test logs of a repetition do not depend on n; repetitions draw differently
        by_rep.setdefault(j.rep, set()).add(frozenset(_names(j.evals["tovk"])))
    assert all(len(s) == 1 for s in by_rep.values()) and by_rep[0] != by_rep[1]
    small = next(j for j in tovk if j.n == 3 and j.rep == 0)
    big = next(j for j in tovk if j.n == 15 and j.rep == 0)
    assert _names(small.train) <= _names(big.train)


def test_authors_protocol_uses_sorted_rotated_folds(real_logs) -> None:
    jobs = make_jobs(real_logs, ["tovk"], ["bc"], ns=(20,), reps=5, protocol="authors")
    x30 = sorted((lg for lg in real_logs if version_of(lg) == 30.0), key=lambda lg: lg.name)
    assert [lg.name for lg in jobs[0].train] == [lg.name for lg in x30[:20]]
    assert [lg.name for lg in jobs[0].evals["tovk"]] == [lg.name for lg in x30[-10:]]
    shift = len(x30) // 5
    assert jobs[1].train[0].name == x30[shift].name
    with pytest.raises(ValueError, match="5 folds"):
        make_jobs(real_logs, ["tovk"], ["bc"], ns=(3,), reps=6, protocol="authors")


def test_tiny_grid_repeats_and_writes_the_report(real_logs, tmp_path) -> None:
    logs = [lg for lg in real_logs if version_of(lg) == 30.0]
    kw = dict(algorithms=("random", "bc", "gail", "bcxgail"), ns=(3,), reps=2, epochs=2, n_test=6,
              progress=False, train_kwargs=TINY)
    a = run_experiment(logs, ["tovk"], tmp_path / "a", executor=LocalExecutor(0), **kw)
    b = run_experiment(logs, ["tovk"], tmp_path / "b", executor=LocalExecutor(2), **kw)
    ja = json.loads((tmp_path / "a" / "results.json").read_text())
    jb = json.loads((tmp_path / "b" / "results.json").read_text())
    assert ja["summary"] == jb["summary"]  # same seed, same numbers, in-process or in a pool
    assert a["meta"]["jobs"] == 8
    cells = ja["summary"]["tovk"]["versions"]["30"]["cells"]
    assert set(cells) == {"random", "bc", "gail", "bcxgail"} and cells["bc"]["3"]["reps"] == 2
    job = ja["jobs"][0]
    assert job["train_logs"] and job["val_logs"] and job["evals"]["tovk"]["test_logs"]
    md = (tmp_path / "a" / "report.md").read_text()
    assert "TOVK, x=30: accuracy (%)" in md and "FOT vs FOT floor" in md
    assert (tmp_path / "a" / "accuracy_tovk.png").stat().st_size > 0
    assert (tmp_path / "a" / "traces_tovk.png").stat().st_size > 0
    again = run_experiment(logs, ["tovk"], tmp_path / "a", executor=LocalExecutor(0), **kw)
    assert again["meta"]["jobs_reused"] == 8 and again["results"] == a["results"]


def test_dask_executor_gives_the_local_numbers(real_logs, tmp_path) -> None:
    distributed = pytest.importorskip("distributed")
    logs = [lg for lg in real_logs if version_of(lg) == 30.0]
    kw = dict(algorithms=("random", "bc"), ns=(3,), reps=1, epochs=2, n_test=6, progress=False, train_kwargs=TINY)
    local = run_experiment(logs, ["tovk"], tmp_path / "local", executor=LocalExecutor(0), **kw)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        remote = run_experiment(logs, ["tovk"], tmp_path / "dask", executor=DaskExecutor(client), **kw)
    assert [r["evals"] for r in remote["results"]] == [r["evals"] for r in local["results"]]

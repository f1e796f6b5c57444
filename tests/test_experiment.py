"""The experiment grid on a tiny setting: version labels and choices, log splits, determinism,
report files, resuming, the Dask path, and the car twin (a second system) end to end."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from envi_py.controllers import ControllerSpec
from envi_py.executor import DaskExecutor, LocalExecutor
from envi_py.experiments.grid import make_jobs
from envi_py.experiments.report import paper_accuracy
from envi_py.experiments.run import run_experiment
from envi_py.experiments.versions import VersionChoice, version_label, versions_of
from envi_py.system import SystemDescription, lane_keeping, load_system
from envi_py.twin.car import CAR_GAINS, CAR_TRAINED, CAR_UNSEEN, generate_car_versions

TINY = {"hidden": (8,), "eval_every": 2, "horizon": 10, "disc_hidden": (8,), "value_hidden": (8,)}
LANE = lane_keeping()
CAR = load_system("car")
CAR_LABELS = [f"kp_steer={ks:g},kp_speed={kv:g}" for ks, kv in CAR_GAINS]
CAR_TRAIN = tuple(CAR_LABELS[i] for i in CAR_TRAINED)
CAR_NEW = tuple(CAR_LABELS[i] for i in CAR_UNSEEN)


def _names(logs) -> set[str]:
    return {lg.name for lg in logs}


def _label(lg) -> str:
    return version_label(lg.controller, LANE)


@pytest.fixture(scope="module")
def car_logs():
    """9 runs of 60 rows of each of the five shipped car versions (3 train, 2 validate, 4 test)."""
    return generate_car_versions(9, steps=60, seed=5)


def test_labels_name_versions_by_their_parameters() -> None:
    assert version_label(ControllerSpec("lane-keeping", {"x": 30.0}), LANE) == "x=30"
    car = CAR.controller_for({"kp_steer": 0.8, "kp_speed": 18.0})
    assert version_label(car, CAR) == "kp_steer=0.8,kp_speed=18"
    bare = SystemDescription("bare", LANE.schema)  # names no version parameters: the controller's label
    spec = ControllerSpec("lane-keeping", {"x": 12.5})
    assert version_label(spec, bare) == spec.label() == "lane-keeping(x=12.5)"


def test_car_versions_are_chosen_by_label_with_numbers_compared_as_numbers(car_logs) -> None:
    pool = versions_of(car_logs, CAR)
    assert list(pool) == sorted(CAR_LABELS, key=lambda s: [float(p.split("=")[1]) for p in s.split(",")])
    written = ("kp_steer=0.80,kp_speed=18.0", "kp_steer=2, kp_speed=18", CAR_TRAIN[2])
    jobs, plan = make_jobs(
        car_logs,
        ["tmvk", "tmvu"],
        ["bc"],
        ns=(3,),
        reps=1,
        n_val=2,
        n_test=4,
        versions=VersionChoice(train=written, unseen=CAR_NEW),
    )
    assert plan.train["tmvk"] == CAR_TRAIN and plan.eval["tmvk"] == CAR_TRAIN and plan.eval["tmvu"] == CAR_NEW
    (job,) = jobs

    def label(lg: Any) -> str:
        return version_label(lg.controller, CAR)

    assert {label(lg) for lg in job.train} == set(CAR_TRAIN) and len(job.train) == 3 * 3
    assert {label(lg) for lg in job.evals["tmvu"]} == set(CAR_NEW) and len(job.evals["tmvu"]) == 2 * 9
    assert not _names(job.evals["tmvk"]) & _names(job.train + job.val)
    only = make_jobs(
        car_logs,
        ["tmvk"],
        ["bc"],
        ns=(3,),
        reps=1,
        n_val=2,
        n_test=4,
        versions=VersionChoice(train=CAR_TRAIN, eval=CAR_TRAIN[:1]),
    )[1]
    assert only.eval["tmvk"] == CAR_TRAIN[:1]


def test_without_version_parameters_versions_are_chosen_by_the_controllers_label(car_logs) -> None:
    bare = SystemDescription("bare", CAR.schema)  # e.g. drafted without [versions]
    spec = car_logs[0].controller
    assert spec.label().startswith("combine(loops=[pid(")
    jobs, plan = make_jobs(
        car_logs,
        ["tovk"],
        ["bc"],
        ns=(3,),
        reps=1,
        n_val=2,
        n_test=4,
        system=bare,
        versions=VersionChoice(tovk=spec.label()),
    )
    assert plan.train["tovk"] == (spec.label(),) and {lg.controller for lg in jobs[0].train} == {spec}


def test_the_papers_figures_belong_to_the_papers_versions_only() -> None:
    assert paper_accuracy("tmvk", "x=30")["bcxgail"] == (98.78, 99.20, 99.33)
    assert paper_accuracy("tmvu", "x=40.0")["random"] == 81.60
    assert paper_accuracy("tmvu", "x=30") is None and paper_accuracy("tovk", "x=30.5") is None
    assert paper_accuracy("tovk", "kp_steer=0.8,kp_speed=18") is None and paper_accuracy("tovk", "y=30") is None


@pytest.mark.parametrize(
    "choice, uses, message",
    [
        (VersionChoice(), ["tmvk"], r"tmvk: give --train-versions .*available: kp_steer=0.8,kp_speed=18 \(9 logs\);"),
        (VersionChoice(train=CAR_TRAIN), ["tmvu"], "tmvu: give --unseen-versions"),
        (VersionChoice(), ["tovk"], "tovk: give --tovk-version"),
        (
            VersionChoice(tovk="kp_steer=9,kp_speed=18"),
            ["tovk"],
            r"no logs of version 'kp_steer=9,kp_speed=18'; available",
        ),
        (VersionChoice(tovk="kp_steer=0.8"), ["tovk"], "no logs of version 'kp_steer=0.8'"),  # every parameter needed
        (VersionChoice(train=CAR_TRAIN, unseen=CAR_TRAIN[:1]), ["tmvu"], "never trained on; kp_steer=0.8,kp_speed=18"),
        (VersionChoice(train=CAR_TRAIN, eval=CAR_NEW[:1]), ["tmvk"], "verifies trained versions only"),
        (VersionChoice(train=CAR_TRAIN + CAR_TRAIN[:1]), ["tmvk"], "named twice"),
        (VersionChoice(train=CAR_TRAIN, tovk=CAR_TRAIN[0]), ["tmvk"], "--tovk-version applies to tovk"),
    ],
)
def test_wrong_or_missing_version_choices_are_one_clear_error(car_logs, choice, uses, message) -> None:
    with pytest.raises(ValueError, match=message):
        make_jobs(car_logs, uses, ["bc"], ns=(3,), reps=1, n_val=2, n_test=4, versions=choice)


def test_random_splits_are_disjoint_and_shared_across_n(real_logs) -> None:
    jobs, plan = make_jobs(real_logs, ["tovk", "tmvk", "tmvu"], ["bc"], ns=(3, 15), reps=2, seed=1)
    assert plan.train == {"tovk": ("x=30",), "tmvk": ("x=10", "x=30", "x=50"), "tmvu": ("x=10", "x=30", "x=50")}
    assert plan.eval["tmvu"] == ("x=20", "x=40")  # the paper's versions: the logs are the lane-keeping x ones
    assert {j.family for j in jobs} == {"tovk", "tmv"} and len(jobs) == 2 * 2 * 2
    for j in jobs:
        train, val = _names(j.train), _names(j.val)
        assert not train & val
        for uc, test in j.evals.items():
            assert not _names(test) & (train | val), uc
        if j.family == "tmv":
            assert {_label(lg) for lg in j.evals["tmvu"]} == {"x=20", "x=40"}
            assert {_label(lg) for lg in j.train} == {"x=10", "x=30", "x=50"}
            assert len(j.train) == 3 * j.n
    tovk = [j for j in jobs if j.family == "tovk"]
    by_rep = {}
    for j in tovk:  # the test logs of a repetition do not depend on n; repetitions draw differently
        by_rep.setdefault(j.rep, set()).add(frozenset(_names(j.evals["tovk"])))
    assert all(len(s) == 1 for s in by_rep.values()) and by_rep[0] != by_rep[1]
    small = next(j for j in tovk if j.n == 3 and j.rep == 0)
    big = next(j for j in tovk if j.n == 15 and j.rep == 0)
    assert _names(small.train) <= _names(big.train)
    chosen, _ = make_jobs(real_logs, ["tovk"], ["bc"], ns=(3,), reps=1, versions=VersionChoice(tovk="x=10"))
    assert {_label(lg) for lg in chosen[0].train + chosen[0].evals["tovk"]} == {"x=10"}


def test_authors_protocol_uses_sorted_rotated_folds(real_logs) -> None:
    jobs, _ = make_jobs(real_logs, ["tovk"], ["bc"], ns=(20,), reps=5, protocol="authors")
    x30 = sorted((lg for lg in real_logs if _label(lg) == "x=30"), key=lambda lg: lg.name)
    assert [lg.name for lg in jobs[0].train] == [lg.name for lg in x30[:20]]
    assert [lg.name for lg in jobs[0].evals["tovk"]] == [lg.name for lg in x30[-10:]]
    shift = len(x30) // 5
    assert jobs[1].train[0].name == x30[shift].name
    with pytest.raises(ValueError, match="5 folds"):
        make_jobs(real_logs, ["tovk"], ["bc"], ns=(3,), reps=6, protocol="authors")


def test_tiny_grid_repeats_and_writes_the_report(real_logs, tmp_path) -> None:
    logs = [lg for lg in real_logs if _label(lg) == "x=30"]
    kw = {
        "algorithms": ("random", "bc", "gail", "bcxgail"),
        "ns": (3,),
        "reps": 2,
        "epochs": 2,
        "n_test": 6,
        "progress": False,
        "train_kwargs": TINY,
    }
    a = run_experiment(logs, ["tovk"], tmp_path / "a", executor=LocalExecutor(0), **kw)
    run_experiment(logs, ["tovk"], tmp_path / "b", executor=LocalExecutor(2), **kw)
    ja = json.loads((tmp_path / "a" / "results.json").read_text())
    jb = json.loads((tmp_path / "b" / "results.json").read_text())
    assert ja["summary"] == jb["summary"]  # same seed, same numbers, in-process or in a pool
    assert a["meta"]["jobs"] == 8 and a["meta"]["versions"] == {"tovk": {"train": ["x=30"], "eval": ["x=30"]}}
    version = ja["summary"]["tovk"]["versions"]["x=30"]
    cells = version["cells"]
    assert set(cells) == {"random", "bc", "gail", "bcxgail"} and cells["bc"]["3"]["reps"] == 2
    assert version["goals"][0] == "steady_count" and len(version["goals"]) == 8  # the paper's eight metrics
    assert all(len(cells[a]["3"]["kld"]) == 2 for a in cells)  # the lane-keeping preset has its KLD
    job = ja["jobs"][0]
    assert job["train_logs"] and job["val_logs"] and job["evals"]["tovk"]["test_logs"]
    assert job["evals"]["tovk"]["kld_geomean"] > 0
    assert set(job["evals"]["tovk"]["groups"][0]["traces"]["real"]) == {"color"}
    md = (tmp_path / "a" / "report.md").read_text()
    assert "TOVK, x=30: accuracy (%)" in md and "FOT vs FOT floor" in md and "safety/comfort KLD" in md
    assert "geometric-mean KLD" in md
    n_real = job["evals"]["tovk"]["groups"][0]["n_real"]  # every figure says how many runs it rests on
    assert version["runs"]["real"] == [n_real] and f"compares {n_real} real test runs" in md
    assert f"two halves of {n_real // 2} real runs each" in md
    assert (tmp_path / "a" / "report_figures" / "accuracy_tovk.png").stat().st_size > 0
    assert (tmp_path / "a" / "report_figures" / "traces_tovk.png").stat().st_size > 0
    assert '<img src="data:image/png;base64,' in (tmp_path / "a" / "report.html").read_text()
    again = run_experiment(logs, ["tovk"], tmp_path / "a", executor=LocalExecutor(0), **kw)
    assert again["meta"]["jobs_reused"] == 8 and again["results"] == a["results"]


def test_dask_executor_gives_the_local_numbers(real_logs, tmp_path) -> None:
    distributed = pytest.importorskip("distributed")
    logs = [lg for lg in real_logs if _label(lg) == "x=30"]
    kw = {
        "algorithms": ("random", "bc"),
        "ns": (3,),
        "reps": 1,
        "epochs": 2,
        "n_test": 6,
        "progress": False,
        "train_kwargs": TINY,
    }
    local = run_experiment(logs, ["tovk"], tmp_path / "local", executor=LocalExecutor(0), **kw)
    with (
        distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = run_experiment(logs, ["tovk"], tmp_path / "dask", executor=DaskExecutor(client), **kw)
    assert [r["evals"] for r in remote["results"]] == [r["evals"] for r in local["results"]]


def test_car_grid_runs_tmvk_and_tmvu_end_to_end(car_logs, tmp_path) -> None:
    kw = {
        "algorithms": ("random", "bc"),
        "ns": (3,),
        "reps": 1,
        "epochs": 2,
        "n_val": 2,
        "n_test": 4,
        "progress": False,
        "train_kwargs": TINY,
        "executor": LocalExecutor(0),
    }
    choice = VersionChoice(train=CAR_TRAIN, unseen=CAR_NEW)
    res = run_experiment(car_logs, ["tmvk", "tmvu"], tmp_path, versions=choice, **kw)
    assert res["meta"]["jobs"] == 2 and res["meta"]["system"] == "car"  # tmvk and tmvu share their trainings
    out = json.loads((tmp_path / "results.json").read_text())
    goals = [g.name for g in CAR.goals]
    for uc, labels in (("tmvk", CAR_TRAIN), ("tmvu", CAR_NEW)):
        versions = out["summary"][uc]["versions"]
        assert list(versions) == list(labels)
        for v in versions.values():
            assert v["goals"] == goals and v["floor"]["w1_goal"]  # 4 test logs each: a real-vs-real floor
            assert "kld" not in v["cells"]["bc"]["3"]  # no KLD outside the lane-keeping preset
            assert 0 < v["cells"]["bc"]["3"]["acc"][0] <= 1
        assert out["summary"][uc]["kld_geomean"] == {}
    group = out["jobs"][1]["evals"]["tmvu"]["groups"][0]
    assert group["version"] == CAR_NEW[0] and set(group["traces"]["real"]) == {"color", "distance"}
    assert len(group["traces"]["sim"]["distance"]) == 3 and len(group["traces"]["real"]["distance"][0]) == 60
    md = (tmp_path / "report.md").read_text()
    assert f"## TMVU, {CAR_NEW[1]}: accuracy (%)" in md and "| closest approach |" in md
    assert "safety/comfort KLD" not in md and "paper:" not in md
    for name in ("accuracy_tmvk", "accuracy_tmvu", "traces_tmvk", "traces_tmvu"):
        assert (tmp_path / "report_figures" / f"{name}.png").stat().st_size > 0
    again = run_experiment(car_logs, ["tmvk", "tmvu"], tmp_path, versions=choice, **kw)
    assert again["meta"]["jobs_reused"] == 2
    fewer = VersionChoice(train=CAR_TRAIN, eval=CAR_TRAIN[:2], unseen=CAR_NEW)
    assert (
        make_jobs(
            car_logs, ["tmvk", "tmvu"], ["bc"], ns=(3,), reps=1, n_val=2, n_test=4, train_kwargs=TINY, versions=fewer
        )[0][0].fingerprint()
        != make_jobs(
            car_logs, ["tmvk", "tmvu"], ["bc"], ns=(3,), reps=1, n_val=2, n_test=4, train_kwargs=TINY, versions=choice
        )[0][0].fingerprint()
    )  # another choice of versions is another job


def test_cli_names_the_missing_choice_in_one_line(car_logs, tmp_path, capsys) -> None:
    from envi_py.cli import main
    from envi_py.twin.car import write_car_logs

    write_car_logs(car_logs, tmp_path / "logs")
    code = main(
        [
            "experiment",
            "tmvu",
            "--logs",
            str(tmp_path / "logs"),
            "--system",
            "car",
            "--train-versions",
            *CAR_TRAIN,
            "--workers",
            "0",
            "--out",
            str(tmp_path / "out"),
        ]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert err.startswith("envi experiment: error: tmvu: give --unseen-versions") and CAR_NEW[0] in err


SCRIPT = """
import sys, time
from envi_py.executor import LocalExecutor
ex = LocalExecutor(1)
jobs = ex.map(time.sleep, [60])
next(jobs, None)
"""


def test_a_killed_experiment_leaves_no_worker_behind(tmp_path) -> None:
    import os
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen([sys.executable, "-c", SCRIPT])
    try:
        deadline = time.monotonic() + 60
        workers: list[int] = []
        while not workers and time.monotonic() < deadline:  # the pool's worker: a child of the experiment
            time.sleep(0.2)
            children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
            pids = children.read_text().split() if children.exists() else []
            workers = [int(p) for p in pids if b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()]
        assert workers, "the pool never started a worker"
        time.sleep(3.0)  # it has run its initializer (torch imported) and sleeps in the job
        (worker,) = workers
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            raise AssertionError(f"worker {worker} outlived its killed parent")
    finally:
        if proc.poll() is None:
            proc.kill()


class _Interrupted:
    """An executor that is interrupted before any job finishes (Ctrl-C)."""

    def map(self, fn, items):
        raise KeyboardInterrupt
        yield  # pragma: no cover - makes this a generator

    def close(self) -> None:
        pass


def test_an_interrupted_fresh_run_keeps_the_earlier_journal(real_logs, tmp_path) -> None:
    """``--fresh`` once truncated ``jobs.jsonl`` at its start, so Ctrl-C lost every finished job."""
    logs = [lg for lg in real_logs if _label(lg) == "x=30"]
    kw = {"algorithms": ("random",), "ns": (3,), "reps": 1, "n_val": 2, "n_test": 6, "progress": False}
    run_experiment(logs, ["tovk"], tmp_path / "e", executor=LocalExecutor(0), train_kwargs=TINY, **kw)
    journal = (tmp_path / "e" / "jobs.jsonl").read_bytes()
    with pytest.raises(KeyboardInterrupt):
        run_experiment(logs, ["tovk"], tmp_path / "e", executor=_Interrupted(), resume=False, train_kwargs=TINY, **kw)
    assert (tmp_path / "e" / "jobs.jsonl").read_bytes() == journal and journal
    again = run_experiment(logs, ["tovk"], tmp_path / "e", executor=LocalExecutor(0), train_kwargs=TINY, **kw)
    assert again["meta"]["jobs_reused"] == again["meta"]["jobs"] == 1


def test_the_size_of_a_grid_is_said_before_it_runs():
    """The README's real-log grid starts 120 trainings; the bar's first estimate follows the fast random
    baselines. One line says what is about to run, and that GAIL's jobs are slow."""
    from types import SimpleNamespace

    from envi_py.experiments.run import jobs_summary

    todo = [SimpleNamespace(algorithm=a) for a in ["random"] * 30 + ["bc"] * 30 + ["gail"] * 30 + ["bcxgail"] * 30]
    line = jobs_summary(todo, 4)
    assert line.startswith("envi experiment: 120 training(s) to run (30 random, 30 bc, 30 gail, 30 bcxgail), 4 reused")
    assert "gail and bcxgail take minutes each" in line
    assert "minutes" not in jobs_summary(todo[:60], 0)

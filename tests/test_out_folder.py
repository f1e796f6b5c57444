"""Commands that write logs never mix a new run's logs into an earlier run's folder.

``envi simulate`` and ``envi twin generate`` refuse an ``--out`` that already holds logs (one line:
the folder, how many, ``--force``) before any work; with ``--force`` they delete only the earlier
CSV logs and sidecars, so the folder holds exactly the new run. The demo replaces its own logs;
``envi split`` rewrites all three manifests."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from envi_py.cli import build_parser, main
from envi_py.controllers import ControllerSpec
from envi_py.demo import DemoSize, run_demo
from envi_py.logs import folder_logs, load_logs, refuse_earlier_logs, remove_logs
from envi_py.train import train
from envi_py.twin import generate, write_logs


def run_cli(argv: list[str]) -> tuple[int, str, str]:
    """``envi <argv>`` in process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 2
    return code, out.getvalue(), err.getvalue()


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its content: what an untouched folder keeps."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def csv_names(folder: Path) -> list[str]:
    """The CSV files the reader takes as logs (a dot file is not one)."""
    return sorted(p.name for p in folder.glob("*.csv") if not p.name.startswith("."))


def user_files(folder: Path) -> None:
    """Files a user keeps beside logs: none of them is a log to the reader."""
    (folder / "notes.txt").write_text("keep me\n")
    (folder / "train.json").write_text('{"logs": []}\n')
    (folder / ".hidden.csv").write_text("time,color,angle\n")
    (folder / "sub").mkdir()
    (folder / "sub" / "other.csv").write_text("time,color,angle\n0,1,2\n")


def assert_user_files_kept(folder: Path) -> None:
    assert (folder / "notes.txt").read_text() == "keep me\n"
    assert (folder / "train.json").read_text() == '{"logs": []}\n'
    assert (folder / ".hidden.csv").exists() and (folder / "sub" / "other.csv").exists()


def assert_refused(code: int, err: str, cmd: str, folder: Path, held: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith(f"envi {cmd}"), err
    assert f"--out {folder}: holds {held} of an earlier run" in lines[0] and "--force" in lines[0], lines[0]


@pytest.fixture(scope="module")
def init_logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("init")
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 3, 30, seed=2), d)
    return d


@pytest.fixture(scope="module")
def model(init_logs: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    ckpt = train("bc", load_logs(init_logs), [], epochs=1, hidden=(8, 8), history=5, seed=0)
    return ckpt.save(tmp_path_factory.mktemp("model") / "m.pt")


# ----------------------------------------------------------------------------- the folder's logs


def test_folder_logs_are_the_csv_logs_and_sidecars_the_reader_sees(tmp_path: Path):
    assert folder_logs(tmp_path / "missing") == [] and folder_logs(tmp_path) == []
    user_files(tmp_path)
    (tmp_path / "dir.csv").mkdir()  # a folder named like a log is not one
    assert folder_logs(tmp_path) == []
    refuse_earlier_logs(tmp_path, force=False)  # user files alone are no earlier run
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 10}), 2, 20), tmp_path)
    (tmp_path / "orphan.meta.json").write_text("{}")  # a later orphan.csv would inherit it
    names = [p.name for p in folder_logs(tmp_path)]
    assert names == ["twin_10_0.csv", "twin_10_1.csv", "orphan.meta.json", "twin_10_0.meta.json", "twin_10_1.meta.json"]
    with pytest.raises(ValueError, match=r"--sim .*: holds 2 logs of an earlier run; pass --force"):
        refuse_earlier_logs(tmp_path, force=False, option="--sim")
    refuse_earlier_logs(tmp_path, force=True)  # --force: no refusal, nothing removed yet
    assert len(folder_logs(tmp_path)) == 5
    assert remove_logs(tmp_path) == 2
    assert folder_logs(tmp_path) == []
    assert_user_files_kept(tmp_path)
    (tmp_path / "a.meta.json").write_text("{}")
    with pytest.raises(ValueError, match="holds 1 log sidecar of an earlier run"):
        refuse_earlier_logs(tmp_path, force=False)


# ----------------------------------------------------------------------------- envi simulate


def test_simulate_refuses_a_folder_with_logs_and_force_leaves_exactly_the_new_run(
    init_logs: Path, model: Path, tmp_path: Path
):
    out = tmp_path / "sim"
    base = ["simulate", "--model", str(model), "--init-logs", str(init_logs), "--engine", "torch", "--out", str(out)]
    code, _, err = run_cli([*base, "--runs", "4"])
    assert code == 0, err
    first = csv_names(out)
    assert len(first) == 3 * 4
    user_files(out)
    before = snapshot(out)

    # a smaller second run: refused before any work (a missing model is not even opened), nothing changed
    code, _, err = run_cli([*base, "--runs", "1"])
    assert_refused(code, err, "simulate", out, "12 logs")
    missing = ["simulate", "--model", str(tmp_path / "none.pt"), "--init-logs", str(init_logs), "--out", str(out)]
    code, _, err = run_cli(missing)
    assert_refused(code, err, "simulate", out, "12 logs")
    assert snapshot(out) == before

    # --force with a bad controller: the check fails after the refusal, and the old logs stay
    code, _, err = run_cli([*base, "--runs", "1", "--force", "--controller", "nosuch"])
    assert code == 2 and "nosuch" in err
    assert snapshot(out) == before

    code, stdout, err = run_cli([*base, "--runs", "1", "--force", "--seed", "5"])
    assert code == 0, err
    assert "replaced 12 earlier logs" in stdout
    assert csv_names(out) == sorted(f"{Path(n).stem}-sim0.csv" for n in csv_names(init_logs))
    sims = load_logs(out)
    assert len(sims) == 3 and {lg.meta.provenance["seed"] for lg in sims} == {5}
    assert sorted(p.name for p in out.glob("*.meta.json")) == sorted(n[:-4] + ".meta.json" for n in csv_names(out))
    assert_user_files_kept(out)


def test_simulate_into_an_empty_or_missing_folder_works_as_before(init_logs: Path, model: Path, tmp_path: Path):
    for out in (tmp_path / "new" / "sim", tmp_path / "empty"):
        (tmp_path / "empty").mkdir(exist_ok=True)
        argv = ["simulate", "--model", str(model), "--init-logs", str(init_logs), "--engine", "torch"]
        code, stdout, err = run_cli([*argv, "--out", str(out)])
        assert code == 0 and "replaced" not in stdout, err
        assert len(csv_names(out)) == 3


def test_simulate_force_never_deletes_its_own_initial_logs(init_logs: Path, model: Path, tmp_path: Path):
    d = tmp_path / "logs"
    write_logs(generate(ControllerSpec("lane-keeping", {"x": 30}), 2, 30, seed=3), d)
    before = snapshot(d)
    code, _, err = run_cli(["simulate", "--model", str(model), "--init-logs", str(d), "--out", str(d), "--force"])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "holds the initial log twin_30_0.csv" in lines[0], err
    assert snapshot(d) == before


# ----------------------------------------------------------------------------- envi twin generate


@pytest.mark.parametrize(
    "first, second",
    [
        (["--runs", "5", "--steps", "20"], ["--runs", "2", "--steps", "20"]),
        (
            ["--family", "diffdrive", "--param", "x=30", "--runs", "4", "--steps", "20"],
            ["--family", "diffdrive", "--param", "x=30", "--runs", "1", "--steps", "20"],
        ),
        (
            ["--system", "car", "--runs", "2", "--steps", "20"],
            ["--system", "car", "--version", "0", "--runs", "1", "--steps", "20"],
        ),
    ],
)
def test_twin_generate_refuses_earlier_logs_and_force_replaces_them(
    tmp_path: Path, first: list[str], second: list[str]
):
    out = tmp_path / "logs"
    code, _, err = run_cli(["twin", "generate", *first, "--out", str(out)])
    assert code == 0, err
    n_first = len(csv_names(out))
    user_files(out)
    before = snapshot(out)
    code, _, err = run_cli(["twin", "generate", *second, "--out", str(out)])
    assert_refused(code, err, "twin generate", out, f"{n_first} logs")
    assert snapshot(out) == before

    code, stdout, err = run_cli(["twin", "generate", *second, "--out", str(out), "--force"])
    assert code == 0, err
    assert f"replaced {n_first} earlier logs" in stdout
    logs = load_logs(out)
    n_second = int(second[second.index("--runs") + 1])
    assert len(logs) == n_second == len(csv_names(out)) == len(list(out.glob("*.meta.json")))
    assert_user_files_kept(out)


@pytest.mark.parametrize(
    "bad, why",
    [
        (["--effects", "warp=9"], "warp"),
        (["--system", "car", "--version", "0", "0"], "--version 0 is given twice"),  # once found by the writer
    ],
)
def test_twin_generate_force_with_a_bad_option_keeps_the_earlier_logs(tmp_path: Path, bad: list[str], why: str):
    out = tmp_path / "logs"
    assert run_cli(["twin", "generate", "--runs", "2", "--steps", "20", "--out", str(out)])[0] == 0
    before = snapshot(out)
    code, _, err = run_cli(["twin", "generate", *bad, "--runs", "1", "--steps", "20", "--force", "--out", str(out)])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and why in lines[0], err
    assert snapshot(out) == before


def test_help_says_what_force_deletes():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command").choices
    twin = next(a for a in sub["twin"]._actions if a.dest == "twin_command").choices
    for p in (sub["simulate"], twin["generate"]):
        text = " ".join(p.format_help().split())
        assert "--force" in text and "refused when it already holds logs" in text
        assert ".meta.json sidecars are deleted" in text and "any other file stays" in text


# ----------------------------------------------------------------------------- split and demo


def test_split_rewrites_all_three_manifests(init_logs: Path, tmp_path: Path):
    out = tmp_path / "split"
    assert run_cli(["split", "--logs", str(init_logs), "--test", "1", "--val", "1", "--out", str(out)])[0] == 0
    assert len(json.loads((out / "test.json").read_text())["logs"]) == 1
    assert run_cli(["split", "--logs", str(init_logs), "--out", str(out)])[0] == 0
    for name, n in (("train", 3), ("val", 0), ("test", 0)):  # no test log left from the first split
        assert len(json.loads((out / f"{name}.json").read_text())["logs"]) == n


@pytest.mark.parametrize("blocked", ["val", "test"])
def test_split_writes_no_manifest_when_one_cannot_be_written(init_logs: Path, tmp_path: Path, blocked: str):
    """A folder where a manifest goes: one line naming it, and the earlier split left whole (it once
    rewrote train.json before failing on test.json, naming a hidden temporary file)."""
    out = tmp_path / "split"
    assert run_cli(["split", "--logs", str(init_logs), "--test", "1", "--val", "1", "--out", str(out)])[0] == 0
    (out / f"{blocked}.json").unlink()
    (out / f"{blocked}.json").mkdir()
    before = snapshot(out)
    code, said, err = run_cli(["split", "--logs", str(init_logs), "--test", "1", "--seed", "5", "--out", str(out)])
    assert code == 2 and f"{blocked}.json: exists and is not a file" in err and ".tmp" not in err, err
    assert said == "" and snapshot(out) == before


def test_a_second_demo_replaces_its_own_logs_and_keeps_other_files(tmp_path: Path, capsys):
    """A smaller demo after a larger one: its data/ and sim/ hold exactly its own logs (the stale
    ones would otherwise be read back into its training and verification)."""
    out = tmp_path / "demo"
    big = DemoSize(runs_per_version=6, n_train=2, n_val=1, epochs=1, sim_runs=2)
    small = DemoSize(runs_per_version=5, n_train=2, n_val=1, epochs=1, sim_runs=1)
    run_demo(out, size=big)
    assert len(csv_names(out / "data")) == 30 and len(csv_names(out / "sim")) == 5 * 3 * 2
    (out / "data" / "mine.txt").write_text("keep me\n")
    capsys.readouterr()
    run_demo(out, size=small)
    assert "replaced 60 logs of an earlier demo" in capsys.readouterr().out
    data = load_logs(out / "data")
    assert len(data) == 25 and len(list((out / "data").glob("*.meta.json"))) == 25
    assert len(csv_names(out / "sim")) == 5 * 2 * 1
    assert (out / "data" / "mine.txt").read_text() == "keep me\n"
    report = json.loads((out / "report" / "report.json").read_text())
    assert sum(g["n_real"] for g in report["groups"]) == 10  # two test logs per version: the new run's

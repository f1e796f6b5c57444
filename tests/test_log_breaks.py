"""Rows lost in transit (a dropped frame on the collector's link): the log says where, and no training
window spans the gap, since a window across it would teach a jump the system never made."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from envi_py.controllers import ControllerSpec
from envi_py.dataset import Dataset, Normaliser
from envi_py.logs import Log, LogError, read_log, sidecar_path, write_log
from envi_py.twin import generate


def _with_breaks(log: Log, breaks: tuple[int, ...]) -> Log:
    return Log(log.path, log.time, log.states, log.actions, replace(log.meta, breaks=breaks), log.logged)


@pytest.fixture
def twin_log() -> Log:
    return generate(ControllerSpec("lane-keeping", {"x": 30}), 1, 60, seed=3)[0]


def test_breaks_travel_in_the_sidecar(tmp_path, twin_log):
    path = write_log(_with_breaks(twin_log, (20, 41)), tmp_path / "run.csv")
    assert read_log(path).meta.breaks == (20, 41)
    plain = write_log(twin_log, tmp_path / "plain.csv")
    assert "breaks" not in sidecar_path(plain).read_text()  # a log without lost rows: sidecar unchanged
    assert read_log(plain).meta.breaks == ()


@pytest.mark.parametrize(
    ("breaks", "says"),
    [
        ("[20, 20]", "increasing"),
        ("[0]", "increasing"),
        ("[true]", "increasing"),
        ('"5"', "increasing"),
        ("[60]", "60 rows"),
        ("0", "increasing"),
        ("false", "increasing"),
        ("{}", "increasing"),
    ],
)
def test_a_wrong_break_is_one_line_naming_the_file(tmp_path, twin_log, breaks, says):
    path = write_log(twin_log, tmp_path / "run.csv")
    side = sidecar_path(path)
    side.write_text(side.read_text().rstrip().rstrip("}") + f', "breaks": {breaks}}}')
    with pytest.raises(LogError, match=says) as err:
        read_log(path)
    assert str(tmp_path) in str(err.value) and "\n" not in str(err.value)


def test_training_pairs_never_span_a_break(twin_log):
    """States count rows, so a pair spans a break exactly when its rows are not consecutive."""
    t, hist, brk = len(twin_log), 5, 30
    rows = np.arange(t, dtype=np.float64)[:, None]
    log = Log(None, twin_log.time, rows, np.zeros((t, 1)), replace(twin_log.meta, breaks=(brk,)))
    norm = Normaliser(np.array([0.0, -1.0]), np.array([t - 1.0, 1.0]))
    whole = Dataset.build([log], hist, norm)
    cut = Dataset.build([log], hist, norm, cut_at_breaks=True)
    assert sum(len(y) for y in whole.Y) == t - hist  # lined up with the log's rows (a diagnosis needs that)
    assert sum(len(y) for y in cut.Y) == (brk - hist) + (t - brk - hist)
    for x, y in zip(cut.X, cut.Y):
        first = np.rint(norm.decode(np.column_stack([x[:, 0], x[:, 1]]))[:, 0])  # each window's oldest row
        target = np.rint(norm.decode(np.column_stack([y[:, 0], np.zeros(len(y))]))[:, 0])
        assert np.all(target - first == hist)  # consecutive rows only
        assert np.all((target < brk) | (first >= brk))


def test_a_log_with_no_stretch_longer_than_the_history_is_refused(twin_log):
    log = _with_breaks(twin_log, tuple(range(4, 60, 4)))
    with pytest.raises(ValueError, match="no stretch of more than 5 rows"):
        Dataset.build([log], 5, cut_at_breaks=True)


def test_train_says_which_rows_were_lost(tmp_path, twin_log):
    for i, lg in enumerate(generate(ControllerSpec("lane-keeping", {"x": 30}), 3, 60, seed=4)):
        write_log(_with_breaks(lg, (25,)) if i == 0 else lg, tmp_path / f"log_{i}.csv")
    out = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", "train", "--logs", str(tmp_path), "--epochs", "2", "--quiet"]
        + ["--hidden", "8", "-o", str(tmp_path / "model" / "m.pt")],  # not among the logs it reads
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "log_0.csv: rows are missing before row(s) 25; no training window spans them" in out.stderr


def test_gail_rolls_out_from_the_pieces_with_their_own_rows(twin_log):
    """GAIL's start windows come from the pieces between breaks, and the controller warms up on the
    same rows the model window holds (it used to index logs by piece: IndexError or misaligned rows)."""
    from envi_py.train import train
    from envi_py.train.gail_env import WindowEnv

    logs = [_with_breaks(twin_log, (3,)), generate(ControllerSpec("lane-keeping", {"x": 30}), 1, 60, seed=5)[0]]
    ckpt = train("bc", logs, [], epochs=1, hidden=(8,), history=5, seed=0)
    env = WindowEnv(ckpt, logs, horizon=20, stride=5)
    decoded = ckpt.norm.decode(env.window0.numpy()[:, :, : ckpt.config.channels].astype(np.float64))
    assert np.allclose(decoded, env.start_rows, atol=1e-3)  # window and warm-up rows are the same rows
    assert np.allclose(env.start_rows[0], twin_log.values[3:8])  # the first piece (rows 0-2) is too short
    with pytest.raises(ValueError, match="no stretch of history 5 \\+ horizon 20 rows between its lost rows"):
        WindowEnv(ckpt, [_with_breaks(twin_log, (20, 40))], horizon=20, stride=5)


def test_train_names_the_pauses_in_its_logs(real_dir, tmp_path):
    """The real logs' 9-14 s pauses were flagged only by envi diagnose; training now says so first."""
    logs = [str(real_dir / f"log_10_{i}.csv") for i in (1, 2, 3)]  # log_10_1 pauses 9.4 s after row 35
    out = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", "train", "--logs", *logs, "--pattern", "log_{x}_{run}.csv"]
        + ["--epochs", "2", "--hidden", "8", "--quiet", "-o", str(tmp_path / "m.pt")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    (note,) = [ln for ln in out.stderr.splitlines() if "pause" in ln]
    assert note.startswith("envi train: note: 1 of 3 logs pause inside the log") and "log_10_1.csv" in note


def test_simulate_and_check_say_when_an_initial_window_spans_lost_rows(tmp_path, twin_log):
    from envi_py.train import train

    model = train("bc", [twin_log], [], epochs=1, hidden=(8,), history=5, seed=0).save(tmp_path / "m.pt")
    write_log(_with_breaks(twin_log, (3,)), tmp_path / "init" / "a.csv")
    write_log(_with_breaks(twin_log, (30,)), tmp_path / "init" / "b.csv")  # after the window: nothing to say
    out = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", "simulate", "--model", str(model), "--init-logs", str(tmp_path / "init")]
        + ["--runs", "1", "--engine", "torch", "--out", str(tmp_path / "sim")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    notes = [ln for ln in out.stderr.splitlines() if "note" in ln]
    assert len(notes) == 1 and "a.csv: rows are missing before row 3, inside the initial window of 5 rows" in notes[0]
    # envi check starts paired simulations from each real run's initial window: the same note
    out = subprocess.run(
        [sys.executable, "-m", "envi_py.cli", "check", "--model", str(model), "--real", str(tmp_path / "init")]
        + ["--require", "max_abs_dev(color, 40) <= 35@0.9", "--max-runs", "40", "--batch", "20"]
        + ["--sims-per-start", "2", "--engine", "torch"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    notes = [ln for ln in out.stderr.splitlines() if "note" in ln]
    assert notes == [
        f"envi check: note: {tmp_path / 'init' / 'a.csv'}: rows are missing before row 3, inside the "
        "initial window of 5 rows its simulations start from"
    ], out.stderr


def test_pieces_keep_their_run_context_and_weigh_as_one_log(twin_log):
    """A piece after a break is part of the same run: its context is the run's (from the log's first
    rows, as simulation computes it), and behaviour cloning steps once per log, not once per piece."""
    from envi_py.dataset import context_of
    from envi_py.train import train
    from envi_py.train.bc import per_log_batches

    log = _with_breaks(twin_log, (20, 40))
    whole = Dataset.build([twin_log], 5, context=True)
    cut = Dataset.build([log], 5, whole.norm, context=True, cut_at_breaks=True)
    run_context = context_of(whole.z[0][:5], whole.n_state)
    assert len(cut.contexts) == 3 and all(np.allclose(c, run_context) for c in cut.contexts)
    assert all(np.allclose(x[:, -run_context.size :], run_context) for x in cut.X)
    ckpt = train("bc", [log, twin_log], [], epochs=1, hidden=(8,), history=5, seed=0)
    xs, ys, _, groups = per_log_batches(ckpt, ckpt.dataset([log, twin_log], cut_at_breaks=True))
    assert groups == [[0, 1, 2], [3]] and [len(y) for y in ys] == [3 * (20 - 5), 60 - 5]

"""End to end on a pseudo-terminal: the simulated brick (a subprocess running the unchanged brick
program) and envi-collect. Timing is only sanity-checked here; figures belong in the report."""

from __future__ import annotations

import json
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from envi_py.controllers import BangBang
from envi_py.dataset import Normaliser
from envi_py.logs import LANE_KEEPING_SCHEMA, load_logs, read_log
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord
from firmware_bridge.brick import protocol as P
from firmware_bridge.brick.identity import program_hash
from firmware_bridge.host import collect
from firmware_bridge.host.brick_sim import BRICK_DIR
from firmware_bridge.host.inject import CheckpointModel
from firmware_bridge.host.ledger import LEDGER_NAME
from firmware_bridge.host.lock import LOCK_NAME

from .conftest import make_log

ROOT = Path(__file__).resolve().parents[1]


class BrickSim:
    """``python -m firmware_bridge.host.brick_sim`` on a symlinked pty, stopped at teardown."""

    def __init__(self, tmp: Path, *args: str) -> None:
        self.link = tmp / "brick"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "firmware_bridge.host.brick_sim", "--link", str(self.link), *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        ready, _, _ = select.select([self.proc.stdout], [], [], 30)
        assert ready, "simulated brick did not start in 30 s"
        assert self.proc.stdout.readline().strip() == str(self.link)

    def stop(self) -> str:
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # never leave it running, even when a test already failed
            self.proc.kill()
            _, err = self.proc.communicate(timeout=30)
        return err


@pytest.fixture
def sim(tmp_path: Path):
    s = BrickSim(tmp_path)
    yield s
    s.stop()


def collect_ok(*argv: str) -> None:
    assert collect.main([*argv, "--quiet"]) == 0


def ledger_ends(folder: Path) -> dict[str, dict]:
    """The ledger's end entry of each run, by run name."""
    entries = [json.loads(line) for line in (folder / LEDGER_NAME).read_text().splitlines()]
    return {e["run"]: e for e in entries if e["event"] == "end"}


def meta(path: Path) -> dict:
    return json.loads(path.with_name(path.stem + ".meta.json").read_text())


def check_rows_follow_controller(log) -> None:
    want = BangBang(x=log.param["x"], threshold=log.param["threshold"])(log.states)
    np.testing.assert_array_equal(log.actions, want)


def test_field_runs_zero_loss(sim: BrickSim, tmp_path: Path) -> None:
    out = tmp_path / "logs"
    collect_ok("--port", str(sim.link), "--runs", "3", "--duration", "4s", "--out", str(out))
    logs = load_logs(out)
    assert [lg.name for lg in logs] == ["log_30_0.csv", "log_30_1.csv", "log_30_2.csv"]
    for lg in logs:
        prov = lg.meta.provenance
        assert lg.meta.source == "fot" and lg.meta.controller == {
            "name": "lane-keeping",
            "params": {"x": 30.0, "threshold": 40.0},
        }
        assert prov["complete"] and prov["lost_frames"] == {"brick_to_host": 0, "host_to_brick": 0}
        # a loaded machine may make the simulated brick overrun and skip a tick: that is a gap in the
        # log, counted as skipped, but never a lost frame
        assert len(lg) == 100 - prov["skipped_ticks"]
        assert sum(b - a + 1 for a, b in prov["gaps"]) == prov["skipped_ticks"]
        assert prov["crc_errors"] == {"at_host": 0, "at_brick": 0}
        assert prov["brick"]["program_hash"] == program_hash(str(BRICK_DIR))
        assert prov["link"] == str(sim.link) and prov["controller_mismatches"] == 0
        timing = prov["timing"]["brick_period_ms"]
        assert 30 < timing["mean"] < 50  # sanity only: the machine may be loaded
        assert set(timing) >= {"mean", "sd", "p99", "max", "rate_hz"}
        assert prov["clock"]["ping_rtt_ms"]["n"] == 10
        check_rows_follow_controller(lg)
        assert lg.states.min() < 40 < lg.states.max()  # the world made it cross the edge
        assert prov["rows_sent"] == len(lg) and prov["rows_lost"] == 0 and prov["foreign_frames_at_host"] == 0
    ends = ledger_ends(out)
    assert {k: (e["status"], e["rows"], e["rows_lost"], e["file"]) for k, e in ends.items()} == {
        lg.name[:-4]: ("complete", len(lg), 0, lg.name) for lg in logs
    }
    assert not list(out.glob(".*"))  # no temporary files left


def journal_runs(path: Path) -> dict[int, list[tuple[str, P.Message]]]:
    """The brick's frames per run: from its STARTED to the next handshake (or the disconnect).

    Frames lost just before the STARTED (a last PONG) belong to the run too: the host can only
    notice them from the sequence number of the next frame it gets, which is the run's first.
    """
    runs: dict[int, list] = {}
    current: list | None = None
    unnoticed: list = []  # lost frames since the last one that arrived
    for line in path.read_text().splitlines():
        kind, hexframe = line.split()
        msgs = P.Decoder().feed(bytes.fromhex(hexframe))
        if kind == "garbage" or not msgs:
            continue
        m = msgs[0]
        if m.type == P.HANDSHAKE:
            current = None
        if m.type == P.STARTED:
            current = runs.setdefault(m.fields[0], [])
            current.extend(unnoticed)
        if current is not None and kind != "dup":
            current.append((kind, m))
        unnoticed = [*unnoticed, (kind, m)] if kind in ("drop", "flip") else []
        if kind == "disconnect":
            current = None
    return runs


def row_key(t: float, c: float, a: float) -> tuple[int, int, int]:
    return int(t), round(c * 100), round(a * 100)


FAULTS = "garbage=0.05,flip=0.04,drop=0.04,dup=0.04,rx_drop=0.03,disconnect=420,seed=5"


def test_faults_are_counted_and_no_row_is_lost_or_corrupted(tmp_path: Path) -> None:
    journal = tmp_path / "journal.txt"
    s = BrickSim(tmp_path, "--faults", FAULTS, "--journal", str(journal))
    out = tmp_path / "logs"
    try:
        # a disconnect makes a run incomplete: exit 2 unless partial runs are accepted
        collect_ok("--port", str(s.link), "--runs", "5", "--duration", "4s", "--out", str(out), "--accept-partial")
    finally:
        err = s.stop()
    assert "injected disconnect" in err
    runs = journal_runs(journal)
    logs = {int(lg.name.split("_")[2].split(".")[0]): lg for lg in load_logs(out)}
    assert sorted(logs) == [0, 1, 2, 3, 4]
    incomplete = [k for k, lg in logs.items() if not lg.meta.provenance["complete"]]
    assert len(incomplete) == 1 and logs[incomplete[0]].meta.provenance["end_reason"] == "disconnect"
    faults = {"drop": 0, "flip": 0}
    for lg in logs.values():
        prov = lg.meta.provenance
        check_rows_follow_controller(lg)
        recorded = [row_key(t, c, a) for t, c, a in zip(lg.time, lg.states[:, 0], lg.actions[:, 0])]
        frames = runs[prov["brick_run_id"]]
        intact = [
            row_key(m.fields[2], m.fields[3] / 100, m.fields[4] / 100)
            for kind, m in frames
            if kind == "sent" and m.type == P.TELEMETRY
        ]
        lost = sum(kind in ("drop", "flip") for kind, _ in frames)
        for kind, _ in frames:
            faults[kind] = faults.get(kind, 0) + 1
        missing = sum(g[1] - g[0] + 1 for g in prov["gaps"])
        if prov["complete"]:
            assert recorded == intact  # every intact row, in order, nothing else
            assert prov["lost_frames"]["brick_to_host"] == lost  # every dropped or flipped frame counted
            assert len(lg) + missing == 100
            sent = sum(m.type == P.TELEMETRY for _, m in frames)
            assert prov["rows_sent"] == sent and prov["rows_lost"] == sent - len(lg)
        else:
            assert recorded == intact[: len(recorded)]  # what arrived before the cut is intact
            assert prov["lost_frames"]["brick_to_host"] >= missing
    assert faults["drop"] > 5 and faults["flip"] > 5  # the faults did happen
    total = {
        key: sum(lg.meta.provenance[key] for lg in logs.values())
        for key in ("duplicates_at_host", "discarded_bytes_at_host", "malformed_at_host")
    }
    assert total["duplicates_at_host"] > 0 and total["discarded_bytes_at_host"] > 0
    assert sum(lg.meta.provenance["crc_errors"]["at_host"] for lg in logs.values()) > 0
    assert not list(out.glob(".*"))


def tiny_checkpoint(path: Path) -> Path:
    """A small model trained for a moment on lane-keeping-like traces: enough to inject colours."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    t = np.arange(200)
    logs = [
        make_log(np.clip(40 + 30 * np.sin(t / (3 + i)) + rng.normal(0, 2, t.size), 5, 75).round()) for i in range(3)
    ]
    norm = Normaliser.fit(logs)
    cfg = ModelConfig(n_state=1, n_action=1, hidden=(16, 16))
    model = EnvModel(cfg)
    z = np.concatenate([norm.encode(lg.values) for lg in logs]).astype(np.float32)
    x = torch.from_numpy(np.stack([z[i : i + cfg.history].reshape(-1) for i in range(len(z) - cfg.history)]))
    y = torch.from_numpy(z[cfg.history :, :1])
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(150):
        opt.zero_grad()
        loss = torch.mean((model(x)[0] - y) ** 2)
        loss.backward()
        opt.step()
    return Checkpoint(model.eval(), norm, LANE_KEEPING_SCHEMA, TrainingRecord("bc", 0, period_ms=40.0)).save(path)


def test_hil_actions_are_the_controller_on_injected_colours(sim: BrickSim, tmp_path: Path) -> None:
    ckpt_path = tiny_checkpoint(tmp_path / "tiny.pt")
    init = make_log(np.array([75, 74, 70, 60, 45, 30, 20, 15, 20, 35, 50, 60], dtype=float))
    init_path = tmp_path / "init.csv"
    from envi_py.logs import write_log

    write_log(init, init_path)
    out = tmp_path / "hil"
    collect_ok(
        "--port",
        str(sim.link),
        "--runs",
        "2",
        "--duration",
        "4s",
        "--out",
        str(out),
        "--inject",
        str(ckpt_path),
        "--init-log",
        str(init_path),
    )
    model = CheckpointModel(Checkpoint.load(ckpt_path))
    for name in ("hil_30_0.csv", "hil_30_1.csv"):
        lg = read_log(out / name)
        prov = lg.meta.provenance
        assert lg.meta.source == "hil" and prov["mode"] == "lockstep" and prov["complete"]
        # lock-step never skips a tick; only a host stalled for two periods (a loaded machine) makes
        # a timeout, which is reported and leaves no row
        assert len(lg) == 100 - prov["hil"]["timeouts"] and prov["lost_frames"]["brick_to_host"] == 0
        check_rows_follow_controller(lg)  # the brick's real controller answered every injected colour
        assert len(prov["hil"]["rtt_ms_per_row"]) == len(lg)
        # and the colours are the model's predictions from the window the host kept
        model.reset()
        window = init.values[: model.history].copy()
        for k in range(len(lg)):
            want = round(min(100.0, max(0.0, model(window))), 2)
            assert lg.states[k, 0] == pytest.approx(want, abs=0.0051), k
            window = np.concatenate([window[1:], lg.values[k : k + 1]])
        assert np.ptp(lg.states) > 0  # the model did not just emit one constant


def test_refused_hil_runs_reserve_nothing_so_the_next_collection_is_clean(
    sim: BrickSim, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    """A bad --init-log, a typo in --inject or a run shorter than one tick is one line, exit 2, and
    leaves no ledger entry behind: a refused run once left a reservation that the next, valid
    collection into the same folder reported as a lost run (and exited 2)."""
    ckpt_path = tiny_checkpoint(tmp_path / "tiny.pt")
    bad_init = tmp_path / "nan.csv"
    bad_init.write_text("time,color,angle\n" + "".join(f"{40 * i},{'nan' if i == 3 else 50},30\n" for i in range(12)))
    out = tmp_path / "hil"
    refusals = [
        (["--inject", str(ckpt_path), "--init-log", str(bad_init)], "nan.csv"),
        (["--inject", "no_such_module:fn"], "--inject no_such_module:fn: cannot import"),
        (["--inject", "firmware_bridge.host.inject:no_such_name"], "cannot import 'no_such_name'"),
        (["--duration", "10ms"], "shorter than one tick"),
    ]
    for extra, said in refusals:
        rc = collect.main(["--port", str(sim.link), "--duration", "4s", "--out", str(out), "--quiet", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and said in err and "Traceback" not in err, err
        assert len(err.strip().splitlines()) == 1, err
    assert not (out / LEDGER_NAME).exists() or not (out / LEDGER_NAME).read_text().strip()
    collect_ok("--port", str(sim.link), "--duration", "1s", "--out", str(out))
    assert ledger_ends(out)["log_30_0"]["status"] == "complete"  # and no earlier run reported lost
    err = capsys.readouterr().err
    assert "unsettled" not in err and " 0 lost run(s)" in err, err


@pytest.mark.parametrize("argv", [["--duration", "0s"], ["--duration", "-1"], ["--init-log", "x.csv"]])
def test_collect_options_refused_before_any_contact(argv: list[str], tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        collect.main(["--port", "/dev/null/none", "--out", str(tmp_path / "o"), *argv])
    assert exc.value.code == 2 and not (tmp_path / "o").exists()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "kill"])
def test_ctrl_c_leaves_only_complete_files(tmp_path: Path, sig: signal.Signals) -> None:
    """Ctrl-C, and a plain kill (SIGTERM) alike: the run under way is written and settled as
    incomplete, never left as a ledger start without an end."""
    sim = BrickSim(tmp_path, "--world", "firmware_bridge.host.world:EdgeWorld")  # the stand-in world
    try:
        ctrl_c(sim, tmp_path, sig)
    finally:
        sim.stop()


def ctrl_c(sim: BrickSim, tmp_path: Path, sig: signal.Signals = signal.SIGINT) -> None:
    out = tmp_path / "logs"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "firmware_bridge.host.collect",
            "--port",
            str(sim.link),
            "--runs",
            "5",
            "--duration",
            "4s",
            "--out",
            str(out),
            "--quiet",
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not (out / "log_30_0.csv").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.5)  # well into the second run
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    assert "interrupted" in err
    assert "1 complete, 1 incomplete, 0 lost run(s)" in err
    names = sorted(p.name for p in out.iterdir())
    assert names == [LEDGER_NAME, LOCK_NAME, "log_30_0.csv", "log_30_0.meta.json", "log_30_1.csv", "log_30_1.meta.json"]
    ends = ledger_ends(out)
    assert ends["log_30_1"]["status"] == "incomplete" and ends["log_30_1"]["reason"] == "interrupted"
    # the brick said how many rows it sent before the STOP: every one of them is in the log
    assert ends["log_30_1"]["rows_sent"] == ends["log_30_1"]["rows"] and ends["log_30_1"]["rows_lost"] == 0
    first, second = read_log(out / "log_30_0.csv"), read_log(out / "log_30_1.csv")
    assert first.meta.provenance["complete"] and len(first) == 100
    assert not second.meta.provenance["complete"] and second.meta.provenance["end_reason"] == "interrupted"
    assert 0 < len(second) < 100
    check_rows_follow_controller(second)


def test_hil_over_a_faulty_link_reports_every_timeout(tmp_path: Path) -> None:
    sim = BrickSim(
        tmp_path,
        "--world",
        "firmware_bridge.host.world:EdgeWorld",
        "--faults",
        "drop=0.05,flip=0.03,rx_drop=0.05,seed=2",
    )
    out = tmp_path / "hil"
    try:
        collect_ok(
            "--port",
            str(sim.link),
            "--duration",
            "4s",
            "--out",
            str(out),
            "--inject",
            "firmware_bridge.host.inject:WorldModel",
            "--accept-partial",
        )
    finally:
        sim.stop()
    lg = read_log(out / "hil_30_0.csv")
    prov = lg.meta.provenance
    check_rows_follow_controller(lg)
    hil = prov["hil"]
    # a lost colour (host->brick) or a lost answer (brick->host, so no next colour) leaves the brick
    # waiting in vain: it says so for that tick instead of making a value up
    assert hil["timeouts"] > 0 and prov["lost_frames"]["host_to_brick"] > 0
    assert prov["brick_report"]["timeouts"] == hil["timeouts"]
    missing = {k for a, b in prov["gaps"] for k in range(a, b + 1)}
    assert set(hil["timeout_ticks"]) <= missing
    assert len(lg) + len(missing) == 100
    assert len(missing) <= hil["timeouts"] + prov["lost_frames"]["brick_to_host"]

"""envi-collect killed with SIGKILL at random ticks and restarted: no run is lost unreported or mixed.

A 10-run session against the simulated brick on a pty; the collector is killed 20 times, each
time at a seeded random tick of its first or second run (counted from the brick's own journal of
the frames it sent), and restarted, asking for the runs still missing. A kill that comes late on a loaded
machine (its run already ended) lands in the next run instead, and the session goes on until all 20
kills and 10 complete runs happened. Afterwards every log must be exactly one run's rows as the brick
sent them, no file may ever have changed once written, and every row the brick sent must be either in a
log or reported lost in the ledger.
"""

from __future__ import annotations

import hashlib
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from envi_py.logs import load_logs, read_log
from firmware_bridge.brick import protocol as P
from firmware_bridge.host.ledger import LEDGER_NAME, Ledger
from firmware_bridge.host.lock import LOCK_NAME

from .test_bridge_pty import ROOT, BrickSim

SEED = 16
RUNS = 10
KILLS = 20
PERIOD_MS = 20
TICKS = 50  # per run: 1 s at 20 ms, a little longer than a restart: some orphans still run, some ended
UMASK = 0o027  # so a log must come out 0640, not 0600


class Journal:
    """The brick's journal read as it grows: every TELEMETRY frame with data, by run id."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.offset = 0
        self.rest = b""
        self.rows: dict[int, list[tuple[int, int, int, int]]] = {}  # run id -> (tick, ms, colour, angle)
        self.total = 0

    def update(self) -> int:
        if not self.path.exists():
            return self.total
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            data = fh.read()
        self.offset += len(data)
        lines = (self.rest + data).split(b"\n")
        self.rest = lines.pop()
        for line in lines:
            kind, hexframe = line.decode().split()
            msgs = P.Decoder().feed(bytes.fromhex(hexframe))
            assert kind == "sent" and len(msgs) == 1, line  # no faults injected
            m = msgs[0]
            if m.type == P.TELEMETRY and not m.fields[6] & P.FLAG_TIMEOUT:
                rid, tick, stamp, colour, angle = m.fields[:5]
                self.rows.setdefault(rid, []).append((tick, stamp, colour, angle))
                self.total += 1
        return self.total


def digest(folder: Path) -> dict[str, str]:
    """Every log and sidecar's hash (the ledger is appended to, the lock file holds its holder's pid)."""
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.iterdir())
        if p.name not in (LEDGER_NAME, LOCK_NAME)
    }


def complete_logs(out: Path) -> int:
    if not (out / LEDGER_NAME).exists():
        return 0
    return sum(e.get("status") == "complete" for e in ledger(out) if e["event"] == "end")


def ledger(out: Path) -> list[dict]:
    return Ledger(out).entries  # as a collector reads it (a line torn by a kill is skipped)


def ended_runs(out: Path) -> set[int]:
    """Run ids the ledger records as settled."""
    if not (out / LEDGER_NAME).exists():
        return set()
    return {e["run_id"] for e in ledger(out) if e["event"] == "end"}


def own_runs(out: Path, pid: int) -> list[int]:
    """Run ids the collector with this pid started, in order (from the ledger)."""
    if not (out / LEDGER_NAME).exists():
        return []
    return [e["run_id"] for e in ledger(out) if e["event"] == "start" and e.get("pid") == pid]


def launch(link: Path, out: Path, runs: int, duration_ms: int, log: Path, *extra: str) -> subprocess.Popen:
    """envi-collect in a subprocess under umask 027 (the shell sets it and execs: same pid, as a user's)."""
    with open(log, "w") as err:
        return subprocess.Popen(
            [
                "sh",
                "-c",
                f'umask {UMASK:03o} && exec "$0" "$@"',
                sys.executable,
                "-m",
                "firmware_bridge.host.collect",
                "--port",
                str(link),
                "--runs",
                str(runs),
                "--duration",
                f"{duration_ms}ms",
                "--out",
                str(out),
                "--pings",
                "3",
                "--quiet",
                *extra,
            ],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
            stderr=err,
        )


def test_a_run_left_going_by_a_killed_collector_is_stopped_and_reported_lost(tmp_path: Path) -> None:
    """The issue's case: killed mid-run, restarted with the same folder while the brick is still in
    that run. The new collector stops it, reports it lost and records only its own run, under a new
    name."""
    journal = Journal(tmp_path / "journal.txt")
    out = tmp_path / "logs"
    sim = BrickSim(
        tmp_path,
        "--period",
        str(PERIOD_MS),
        "--world",
        "firmware_bridge.host.world:EdgeWorld",
        "--journal",
        str(journal.path),
    )
    procs: list[subprocess.Popen] = []
    try:
        first = launch(sim.link, out, 1, 10_000, tmp_path / "first.err")  # a 500-tick run
        procs.append(first)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and first.poll() is None:
            journal.update()
            mine = own_runs(out, first.pid)
            if mine and len(journal.rows.get(mine[0], [])) >= 10:
                break
            time.sleep(0.005)
        first.send_signal(signal.SIGKILL)
        first.wait(timeout=10)
        [orphan] = own_runs(out, first.pid)
        second = launch(sim.link, out, 1, TICKS * PERIOD_MS, tmp_path / "second.err")
        procs.append(second)
        rc = second.wait(timeout=60)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        sim.stop()
    journal.update()
    err = (tmp_path / "second.err").read_text()
    assert rc == 2 and "1 complete, 0 incomplete, 1 lost run(s)" in err and "left unsettled" in err, err
    ends = {e["run_id"]: e for e in ledger(out) if e["event"] == "end"}
    lost = ends[orphan]
    assert (lost["run"], lost["status"], lost["file"], lost["settled_by"]) == (
        "log_30_0",
        "lost",
        None,
        "next collector",
    )
    # stopped long before its 500 ticks, and every row it sent is counted lost
    assert lost["rows_sent"] == len(journal.rows[orphan]) == lost["rows_lost"] < 400
    [log] = load_logs(out)
    assert log.path.name == "log_30_1.csv"  # the orphan's name stays reserved for its ledger entry
    rid = log.meta.provenance["brick_run_id"]
    assert rid != orphan and ends[rid]["status"] == "complete"
    assert [round(c * 100) for c in log.states[:, 0]] == [c for _, _, c, _ in journal.rows[rid]]
    assert log.meta.provenance["rows_lost"] == 0


def test_sigkill_at_random_ticks_never_loses_overwrites_or_mixes_a_run(tmp_path: Path) -> None:
    rng = random.Random(SEED)
    # (its run 0 or 1, at tick); every other kill early in the run, so that the run is still going
    # when the next collector connects and must be stopped, not just settled
    plan = [(rng.randrange(2), rng.randrange(1, 5 if j % 2 else TICKS - 2)) for j in range(KILLS)]
    journal = Journal(tmp_path / "journal.txt")
    out = tmp_path / "logs"
    sim = BrickSim(
        tmp_path,
        "--period",
        str(PERIOD_MS),
        "--world",
        "firmware_bridge.host.world:EdgeWorld",
        "--journal",
        str(journal.path),
    )
    procs: list[subprocess.Popen] = []
    kills = 0
    seen: dict[str, str] = {}  # every file ever written, with its hash: none may change or vanish
    seen_ledger = b""
    last_rc = last_err = None
    interrupted = 0  # kills that landed inside a run (not in the instant its end was recorded)
    killed = False
    try:
        # bounded: each attempt is killed or finishes within 60 s, and at most one misses its kill
        for attempt in range(3 * KILLS + 5):
            complete = complete_logs(out)
            if kills >= KILLS and complete >= RUNS and not killed:
                break
            # while kills are still due, ask for at least one run: a kill that came late (a loaded
            # machine) let a run complete, and the session must still see all its kills
            ask = max(RUNS - complete, 1)
            target = plan[kills] if kills < KILLS else None
            if target is not None and ask == 1:
                target = (0, target[1])
            err_path = tmp_path / f"collect_{attempt}.err"
            proc = launch(sim.link, out, ask, TICKS * PERIOD_MS, err_path)
            procs.append(proc)
            deadline = time.monotonic() + 60
            killed = False
            while proc.poll() is None and time.monotonic() < deadline:
                journal.update()
                mine = own_runs(out, proc.pid)
                if target is None or len(mine) <= target[0]:
                    time.sleep(0.002)
                    continue
                # kill only inside a run that is still going (at least two ticks left by the brick's
                # journal): the target tick of the target run, or if that run already ended, at once
                # in the run after it
                sent = len(journal.rows.get(mine[-1], []))
                due = target[1] if len(mine) == target[0] + 1 else 1
                if due <= sent < TICKS - 2 and mine[-1] not in ended_runs(out):
                    proc.send_signal(signal.SIGKILL)
                    proc.wait(timeout=10)
                    kills += 1
                    killed = True
                    interrupted += mine[-1] not in ended_runs(out)
                    break
                time.sleep(0.002)
            assert proc.poll() is not None, f"collector attempt {attempt} did not finish in 60 s"
            if not killed:
                last_rc, last_err = proc.returncode, err_path.read_text()
                assert last_rc in (0, 2), last_err
            # after every kill and restart: nothing written earlier has changed or gone
            now = digest(out) if out.exists() else {}
            for name, h in seen.items():
                assert now.get(name) == h, f"{name} was replaced or removed (attempt {attempt})"
            seen.update(now)
            text = (out / LEDGER_NAME).read_bytes() if (out / LEDGER_NAME).exists() else b""
            assert text.startswith(seen_ledger), "the ledger was rewritten, not appended to"
            seen_ledger = text
        else:
            raise AssertionError(f"the session did not reach {RUNS} complete runs and {KILLS} kills")
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)
        sim.stop()
    journal.update()
    assert kills == KILLS

    # the last collector settled what the last kill left and says so in its exit code and summary
    summary = last_err.strip().splitlines()[-1]
    assert summary.startswith("envi-collect: ") and "complete" in summary and "recorded +" in summary
    assert (last_rc == 0) == (" 0 incomplete, 0 lost run(s)" in summary and " + 0 lost" in summary), summary

    entries = ledger(out)
    starts = {e["run_id"]: e for e in entries if e["event"] == "start"}
    ends: dict[int, dict] = {}
    for e in entries:
        if e["event"] == "end":
            assert e["run_id"] not in ends, f"run {e['run']} settled twice"
            ends[e["run_id"]] = e
    assert set(ends) == set(starts), "a run was started and never settled"
    assert set(journal.rows) <= set(starts), "the brick ran a run no ledger entry knows"
    assert len({e["run"] for e in starts.values()}) == len(starts), "a run name was handed out twice"

    logs = {lg.path.name: lg for lg in load_logs(out)}  # every log valid
    umask_mode = 0o666 & ~UMASK
    for name, lg in logs.items():
        for p in (lg.path, lg.path.with_name(lg.path.stem + ".meta.json")):
            assert p.stat().st_mode & 0o777 == umask_mode, f"{p.name}: mode {p.stat().st_mode & 0o777:o}"
        prov = lg.meta.provenance
        rid = prov["brick_run_id"]
        sent = journal.rows[rid]
        # exactly the rows the brick sent for that run, in order: one run, nothing else, nothing lost
        got = [(int(t), round(c * 100), round(a * 100)) for t, c, a in zip(lg.time, lg.states[:, 0], lg.actions[:, 0])]
        assert got == [(s, c, a) for _, s, c, a in sent], name
        ticks = np.array([k for k, *_ in sent])
        stamps = np.array([s for _, s, _, _ in sent])
        assert np.all(np.diff(lg.time) > 0)
        # continuous at the brick's period: consecutive ticks except the ones it skipped (an overrun
        # on a loaded machine), and no reading before its tick was due
        assert np.all(np.diff(ticks) >= 1) and np.all(stamps >= ticks * PERIOD_MS)
        assert lg.meta.breaks == tuple(int(i) + 1 for i in np.nonzero(np.diff(ticks) > 1)[0])  # no window spans one
        missing = int(np.sum(np.diff(ticks) - 1)) + int(ticks[0]) + TICKS - 1 - int(ticks[-1])
        assert prov["complete"] and missing == prov["skipped_ticks"] == sum(b - a + 1 for a, b in prov["gaps"])
        assert ends[rid]["file"] == name and ends[rid]["status"] == "complete" and ends[rid]["rows"] == len(lg)
    n_complete = sum(e["status"] == "complete" for e in ends.values())
    assert n_complete == len(logs) >= RUNS

    recorded = lost = 0
    for rid, e in ends.items():
        sent_rows = len(journal.rows.get(rid, []))
        assert e["rows_sent"] == sent_rows, e  # the brick's own count agrees with what it journaled
        assert e["rows"] + e["rows_lost"] == e["rows_sent"], e
        if e["file"] is None:
            assert e["status"] == "lost" and e["rows"] == 0
        else:
            assert len(read_log(out / e["file"])) == e["rows"]
        recorded += e["rows"]
        lost += e["rows_lost"]
    assert recorded + lost == journal.total  # per session: every row sent is recorded or reported lost
    # each kill lost the run it hit, which the next collector reported lost; every other run is complete
    lost_runs = [e for e in ends.values() if e["status"] == "lost"]
    # (a kill can land in the instant a run's end is recorded: it loses nothing, and few may)
    assert len(lost_runs) == interrupted >= KILLS - 2 and len(ends) == n_complete + interrupted
    assert all(e["settled_by"] == "next collector" and e["file"] is None for e in lost_runs)
    assert lost > 0 and not list(out.glob(".*"))  # no staging file left behind
    print(
        f"{kills} kills, {len(ends)} runs started, {len(lost_runs)} lost (rows sent "
        f"{sorted(e['rows_sent'] for e in lost_runs)}); rows {recorded} recorded + {lost} lost = {journal.total} "
        "sent by the brick"
    )

"""Link measurement: N field runs (and a few HIL runs) against the simulated brick on a pty.

``python -m firmware_bridge.host.measure --runs 30 --out DIR`` starts the simulated brick, collects
with ``envi-collect`` and pools the sidecars: loop rate and jitter from the brick's time stamps,
host arrival jitter, lost frames each way, ping round trips and HIL inject-to-action times.
Prints a Markdown table and writes ``DIR/measurement.json``.
"""

from __future__ import annotations

import argparse
import json
import select
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from envi_py.logs import load_logs

from . import collect
from .stats import summary


def _start_sim(link: Path) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_bridge.host.brick_sim", "--link", str(link)], stdout=subprocess.PIPE, text=True
    )
    ready, _, _ = select.select([proc.stdout], [], [], 30)
    if not ready:
        proc.kill()
        raise RuntimeError("simulated brick did not start")
    proc.stdout.readline()
    return proc


def pooled(folder: Path) -> dict[str, Any]:
    logs = load_logs(folder)
    prov = [lg.meta.provenance for lg in logs]
    periods = np.concatenate([np.diff(lg.time) for lg in logs])  # gap-free runs: all ticks consecutive
    host_sd = [p["timing"]["host_arrival_period_ms"]["sd"] for p in prov]
    host_max = [p["timing"]["host_arrival_period_ms"]["max"] for p in prov]
    out: dict[str, Any] = {
        "runs": len(logs),
        "rows": int(sum(len(lg) for lg in logs)),
        "complete": int(sum(p["complete"] for p in prov)),
        "brick_period_ms": summary(periods),
        "rate_hz": round(1000 / float(periods.mean()), 3),
        "host_arrival_period_sd_ms": {"mean": round(float(np.mean(host_sd)), 3), "max": max(host_sd)},
        "host_arrival_period_max_ms": max(host_max),
        "loop_work_us_max": max(p["timing"]["loop_work_us"]["max"] for p in prov),
        "lost_brick_to_host": int(sum(p["lost_frames"]["brick_to_host"] for p in prov)),
        "lost_host_to_brick": int(sum(p["lost_frames"]["host_to_brick"] or 0 for p in prov)),
        "crc_errors": int(sum(p["crc_errors"]["at_host"] + (p["crc_errors"]["at_brick"] or 0) for p in prov)),
        "overruns": int(sum(p["overruns"] for p in prov)),
        "gaps": int(sum(len(p["gaps"]) for p in prov)),
        "ping_rtt_ms": {
            "mean_of_means": round(float(np.mean([p["clock"]["ping_rtt_ms"]["mean"] for p in prov])), 3),
            "max": max(p["clock"]["ping_rtt_ms"]["max"] for p in prov),
        },
        "controller_mismatches": int(sum(p["controller_mismatches"] or 0 for p in prov)),
    }
    hil = [p["hil"] for p in prov if "hil" in p]
    if hil:
        rtt = np.concatenate([h["rtt_ms_per_row"] for h in hil])
        held = [h["inject_held_at_brick_ms"]["mean"] for h in hil]
        out["hil_inject_to_action_ms"] = summary(rtt)
        out["hil_inject_held_at_brick_ms_mean"] = round(float(np.mean(held)), 3)
        out["hil_timeouts"] = int(sum(h["timeouts"] for h in hil))
    return out


def table(name: str, m: dict[str, Any]) -> str:
    p = m["brick_period_ms"]
    rows = [
        f"### {name}: {m['runs']} runs, {m['rows']} rows, {m['complete']} complete",
        "| figure | value |",
        "| --- | --- |",
        f"| loop rate | {m['rate_hz']} Hz |",
        f"| brick period mean / sd / p99 / max | {p['mean']} / {p['sd']} / {p['p99']} / {p['max']} ms |",
        f"| host arrival period sd (mean over runs, worst) / max | {m['host_arrival_period_sd_ms']['mean']}, "
        f"{m['host_arrival_period_sd_ms']['max']} / {m['host_arrival_period_max_ms']} ms |",
        f"| lost frames brick->host / host->brick | {m['lost_brick_to_host']} / {m['lost_host_to_brick']} |",
        f"| CRC errors, overruns, gaps | {m['crc_errors']}, {m['overruns']}, {m['gaps']} |",
        f"| ping round trip mean / max | {m['ping_rtt_ms']['mean_of_means']} / {m['ping_rtt_ms']['max']} ms |",
        f"| loop work max | {m['loop_work_us_max']} us |",
        f"| rows not equal to envi's controller | {m['controller_mismatches']} |",
    ]
    if "hil_inject_to_action_ms" in m:
        h = m["hil_inject_to_action_ms"]
        rows += [
            f"| HIL inject->action mean / p99 / max | {h['mean']} / {h['p99']} / {h['max']} ms |",
            f"| HIL colour held at brick until its tick (mean) | {m['hil_inject_held_at_brick_ms_mean']} ms |",
            f"| HIL net link round trip (mean inject->action minus hold) | "
            f"{round(h['mean'] - m['hil_inject_held_at_brick_ms_mean'], 3)} ms |",
            f"| HIL timeouts | {m['hil_timeouts']} |",
        ]
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m firmware_bridge.host.measure", description=__doc__)
    p.add_argument("--runs", type=int, default=30, help="field runs (default 30)")
    p.add_argument("--hil-runs", type=int, default=5, help="HIL runs against the stand-in world (default 5)")
    p.add_argument("--duration", default="4s")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    proc = _start_sim(args.out / "brick")
    try:
        common = ["--port", str(args.out / "brick"), "--duration", args.duration, "--quiet"]
        collect.main([*common, "--runs", str(args.runs), "--out", str(args.out / "field")])
        if args.hil_runs:
            collect.main(
                [
                    *common,
                    "--runs",
                    str(args.hil_runs),
                    "--out",
                    str(args.out / "hil"),
                    "--inject",
                    "firmware_bridge.host.inject:WorldModel",
                ]
            )
    finally:
        proc.terminate()
        proc.wait(30)
    result = {"field": pooled(args.out / "field")}
    if args.hil_runs:
        result["hil"] = pooled(args.out / "hil")
    (args.out / "measurement.json").write_text(json.dumps(result, indent=1) + "\n")
    print("\n\n".join(table(k, v) for k, v in result.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

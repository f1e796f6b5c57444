"""Peak memory of ``envi simulate`` against the number of runs: it must stay flat (issue 16).

Each size runs ``envi simulate`` in its own process under a small wrapper that reports the peak
resident set of its child (``getrusage(RUSAGE_CHILDREN).ru_maxrss``), so the figures are the
command's own, side by side in one run. Prints a table and writes JSON.

    python benchmarks/bench_simulate_memory.py [--runs 1000 10000 40000] [--out bench_out/simulate_memory.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

WRAPPER = (
    "import resource, subprocess, sys; rc = subprocess.run(sys.argv[1:]).returncode; "
    "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(rc)"
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", type=int, default=[1000, 10000, 40000])
    ap.add_argument("--engine", default="auto", choices=("auto", "native", "torch"))
    ap.add_argument("--out", default="bench_out/simulate_memory.json")
    args = ap.parse_args()
    from envi_py.controllers import ControllerSpec
    from envi_py.train import train
    from envi_py.twin import generate, write_logs

    envi = str(Path(sys.executable).with_name("envi"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        logs = generate(ControllerSpec("lane-keeping", {"x": 30}), 4, 100, seed=0)
        write_logs(logs, d / "logs")
        model = train("bc", logs[:3], [], epochs=2, hidden=(256, 256), seed=0).save(d / "m.pt")
        init = str(sorted((d / "logs").glob("*.csv"))[-1])
        for n in args.runs:
            out = d / f"sim{n}"
            t0 = time.perf_counter()
            done = subprocess.run(
                [
                    sys.executable,
                    "-c",
                    WRAPPER,
                    envi,
                    "simulate",
                    "--model",
                    str(model),
                    "--init-logs",
                    init,
                    "--runs",
                    str(n),
                    "--engine",
                    args.engine,
                    "--out",
                    str(out),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            seconds = time.perf_counter() - t0
            peak_mb = int(done.stdout.strip().splitlines()[-1]) / 1024
            files = sum(1 for _ in out.glob("*.csv"))
            rows.append(
                {
                    "runs": n,
                    "peak_mb": peak_mb,
                    "seconds": seconds,
                    "files": files,
                    "engine": done.stdout.split("engine)")[0].rsplit("(", 1)[-1] if "engine)" in done.stdout else "",
                }
            )
            print(f"{n:>9} runs  peak {peak_mb:7.1f} MB  {seconds:7.1f} s  {files} logs", flush=True)
    growth = (rows[-1]["peak_mb"] - rows[0]["peak_mb"]) / max(1, rows[-1]["runs"] - rows[0]["runs"]) * 1024
    print(f"growth: {growth:.3f} KB per run between {rows[0]['runs']} and {rows[-1]['runs']} runs")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"rows": rows, "kb_per_run": growth}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Closed-loop steps per second of the paper's model (20 -> 256 -> 256 -> 1) with lane-keeping.

Engines: the native engine on 1 and 2 threads, onnxruntime and PyTorch batched (one call per time
step for all runs), onnxruntime and PyTorch batch-1 loops (one call per run per step), against the
machine's ceiling: a large float32 GEMM measured in the same run, converted to steps/s at the
model's ~141,800 FLOP per step. Next to it the arithmetic peak (register-only multiply-adds on the
engine's widest vectors): a library GEMM that does not use them can sit below what the engine reaches. Every
engine does the whole loop (model, decode, controller,
encode, slide the window). Long cases are measured on fewer steps or runs and the rate reported
(``measured`` says how many run-steps were timed), so the whole run takes a few minutes.

    python benchmarks/bench_native.py [--out bench_out/bench_native.json] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from envi_py import native
from envi_py.controllers import ControllerSpec
from envi_py.dataset import Normaliser
from envi_py.export import INPUT, to_onnx
from envi_py.logs import LANE_KEEPING_SCHEMA
from envi_py.model import Checkpoint, EnvModel, ModelConfig, TrainingRecord

FLOP_PER_STEP = 2 * (20 * 256 + 256 * 256 + 256 * 1)  # multiply-adds of the three layers: 141,824
THREADS = 2
SPEC = ControllerSpec("lane-keeping", {"x": 30})


def paper_model(seed: int = 0) -> Checkpoint:
    torch.manual_seed(seed)
    return Checkpoint(
        EnvModel(ModelConfig(1, 1)).eval(),
        Normaliser.from_schema(LANE_KEEPING_SCHEMA),
        LANE_KEEPING_SCHEMA,
        TrainingRecord("bc", seed),
    )


def init_windows(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    color = rng.uniform(5, 80, (n, 10))
    return np.stack([color, np.sign(color - 40) * 30], axis=2)


class Loop:
    """The closed loop around any batched ``predict(x float32 (B, 20)) -> z (B, 1)``, as numpy."""

    def __init__(self, ck: Checkpoint, predict: Callable[[np.ndarray], np.ndarray]) -> None:
        self.norm, self.predict = ck.norm, predict

    def run(self, init: np.ndarray, steps: int) -> None:
        w = self.norm.encode(init).astype(np.float32)
        for _ in range(steps):
            z = self.predict(w.reshape(w.shape[0], -1))[:, 0].astype(np.float64)
            s = np.clip(z * self.norm.half[0] + self.norm.centre[0], 0, 100)
            a = np.sign(s - 40) * 30
            row = self.norm.encode(np.stack([s, a], axis=1)).astype(np.float32)
            w = np.concatenate([w[:, 1:], row[:, None]], axis=1)


def cpu_seconds() -> float:
    """CPU time of this process, all its threads (native, onnxruntime, BLAS and torch pools)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def timed_cpu(fn: Callable[[], None], repeat: int = 1) -> tuple[float, float]:
    """Best wall time of ``repeat`` calls and the CPU time of that call.

    On a shared machine wall time says what other processes left us; CPU time says what the work
    itself costs (spinning thread pools included), so both are reported."""
    best = (float("inf"), float("inf"))
    for _ in range(repeat):
        c0, t0 = cpu_seconds(), time.perf_counter()
        fn()
        wall, cpu = time.perf_counter() - t0, cpu_seconds() - c0
        best = min(best, (wall, cpu))
    return best


def timed(fn: Callable[[], None], repeat: int = 1) -> float:
    return timed_cpu(fn, repeat)[0]


def gemm_ceiling(n: int = 4096) -> dict[str, float]:
    """Best float32 GEMM rate of numpy's BLAS and of PyTorch on all threads, in FLOP/s."""
    a = np.random.default_rng(0).random((n, n), dtype=np.float32)
    a @ a
    np_wall, np_cpu = timed_cpu(lambda: a @ a, 3)
    t = torch.from_numpy(a)
    torch.mm(t, t)
    th_wall, th_cpu = timed_cpu(lambda: torch.mm(t, t), 3)
    flop = 2 * n**3
    return {
        "numpy_flops": flop / np_wall,
        "torch_flops": flop / th_wall,
        "flops": flop / min(np_wall, th_wall),
        "flops_per_cpu_s": flop / min(np_cpu, th_cpu),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench_out/bench_native.json")
    ap.add_argument("--quick", action="store_true", help="smaller budgets (a smoke run, not the figures)")
    args = ap.parse_args(argv)
    if not native.available():
        raise SystemExit("the native engine is not built (pip install -e .)")
    budget = 1e5 if args.quick else 1e6  # run-steps timed per native case
    slow_budget = 1e4 if args.quick else 1e5  # per batched Python case
    loop_budget = 200 if args.quick else 1000  # calls per batch-1 loop case
    repeat = 3  # best of: the machine may be shared, the best run is the least disturbed

    import onnxruntime as ort

    ck = paper_model()
    onnx_bytes = to_onnx(ck).SerializeToString()
    compiled = native.load(onnx_bytes)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = THREADS
    sess = ort.InferenceSession(onnx_bytes, opts, providers=["CPUExecutionProvider"])
    opts1 = ort.SessionOptions()
    opts1.intra_op_num_threads = 1
    sess1 = ort.InferenceSession(onnx_bytes, opts1, providers=["CPUExecutionProvider"])
    torch.set_num_threads(THREADS)

    def torch_predict(x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return ck.model(torch.from_numpy(x))[0].numpy()

    engines: dict[str, Callable[[np.ndarray, int], None]] = {
        "native 1 thread": lambda init, t: native.rollout_metrics(compiled, SPEC, init, t, threads=1),
        "native 2 threads": lambda init, t: native.rollout_metrics(compiled, SPEC, init, t, threads=2),
        "onnxruntime batched": Loop(ck, lambda x: sess.run(None, {INPUT: x})[0]).run,
        "pytorch batched": Loop(ck, torch_predict).run,
        "onnxruntime batch-1 loop": None,
        "pytorch batch-1 loop": None,
    }
    loops = {
        "onnxruntime batch-1 loop": Loop(ck, lambda x: sess1.run(None, {INPUT: x})[0]),
        "pytorch batch-1 loop": Loop(ck, torch_predict),
    }

    peak = native.peak_flops(THREADS)
    ceilings = [gemm_ceiling()]
    rows = []
    for n in (1, 100, 10_000):
        for steps in (25, 1000):
            init = init_windows(n)
            if n == 10_000:
                ceilings.append(gemm_ceiling())  # again next to the largest cases
            for name in engines:
                if name in loops:  # one run at a time: time enough calls, the rate does not depend on N
                    runs = max(1, min(n, int(loop_budget // steps)))
                    t = max(1, min(steps, int(loop_budget)))
                    loops[name].run(init[:1], 2)  # warm up
                    sec, cpu = timed_cpu(lambda: [loops[name].run(init[i : i + 1], t) for i in range(runs)], repeat)
                    measured = runs * t
                else:
                    cap = budget if name.startswith("native") else slow_budget
                    t = max(1, min(steps, int(cap // n)))
                    engines[name](init[:2], 2)  # warm up
                    # Short cases are called often enough to last a while: a few milliseconds
                    # would also count thread pools of the previous engine still spinning.
                    calls = max(1, int(cap // 5 // (n * t)))
                    sec, cpu = timed_cpu(lambda: [engines[name](init, t) for _ in range(calls)], repeat)
                    measured = calls * n * t
                rate = measured / sec
                rows.append(
                    {
                        "engine": name,
                        "N": n,
                        "T": steps,
                        "steps_per_s": rate,
                        "measured_run_steps": measured,
                        "steps_per_cpu_s": measured / max(cpu, 1e-9),
                    }
                )
                print(
                    f"  N={n:>5} T={steps:>4} {name:<26} {rate:>14,.0f} steps/s "
                    f"{measured / max(cpu, 1e-9):>14,.0f} per CPU-s",
                    flush=True,
                )

    ceilings.append(gemm_ceiling())
    ceiling = max(ceilings, key=lambda c: c["flops"])  # the highest: ratios to it are conservative
    ceiling_steps = ceiling["flops"] / FLOP_PER_STEP

    def rate(engine: str, n: int, t: int, key: str = "steps_per_s") -> float:
        return next(r[key] for r in rows if r["engine"] == engine and r["N"] == n and r["T"] == t)

    cpu_ceiling_steps = max(c["flops_per_cpu_s"] for c in ceilings) / FLOP_PER_STEP
    cpu_ratios = {  # per CPU-second: what the work costs, whatever else shares the machine
        "native2/ort_batched@N=10000,T=1000": rate("native 2 threads", 10_000, 1000, "steps_per_cpu_s")
        / rate("onnxruntime batched", 10_000, 1000, "steps_per_cpu_s"),
        "native2/ceiling@N=10000,T=1000": rate("native 2 threads", 10_000, 1000, "steps_per_cpu_s") / cpu_ceiling_steps,
        "native1_batch1/ort_batch1_loop@N=1,T=1000": rate("native 1 thread", 1, 1000, "steps_per_cpu_s")
        / rate("onnxruntime batch-1 loop", 1, 1000, "steps_per_cpu_s"),
    }

    ratios = {
        "native2/ort_batched@N=10000,T=1000": rate("native 2 threads", 10_000, 1000)
        / rate("onnxruntime batched", 10_000, 1000),
        "native2/ceiling@N=10000,T=1000": rate("native 2 threads", 10_000, 1000) / ceiling_steps,
        "native2/ceiling@N=10000,T=25": rate("native 2 threads", 10_000, 25) / ceiling_steps,
        "native2/peak@N=10000,T=1000": rate("native 2 threads", 10_000, 1000) / (peak / FLOP_PER_STEP),
        "native1_batch1/ort_batch1_loop@N=1,T=1000": rate("native 1 thread", 1, 1000)
        / rate("onnxruntime batch-1 loop", 1, 1000),
    }
    targets = {
        "native2/ort_batched@N=10000,T=1000": 1.2,
        "native2/ceiling@N=10000,T=1000": 0.75,
        "native2/ceiling@N=10000,T=25": 0.75,
        "native2/peak@N=10000,T=1000": None,
        "native1_batch1/ort_batch1_loop@N=1,T=1000": 4.0,
    }

    engines_order = list(engines)
    print(f"\nclosed-loop steps/s, paper model 20-256-256-1 + lane-keeping ({native.variant()})")
    print(
        f"GEMM ceiling: {ceiling['flops'] / 1e9:.1f} GFLOP/s = {ceiling_steps:,.0f} steps/s "
        f"at {FLOP_PER_STEP:,} FLOP/step (best of {len(ceilings)} measurements: "
        + ", ".join(f"{c['flops'] / 1e9:.0f}" for c in ceilings)
        + " GFLOP/s)"
    )
    print(
        f"arithmetic peak ({THREADS} threads, register-only multiply-adds): {peak / 1e9:.1f} GFLOP/s "
        f"= {peak / FLOP_PER_STEP:,.0f} steps/s"
    )
    head = f"{'N':>6} {'T':>5} " + " ".join(f"{e:>16.16}" for e in engines_order)
    print(head)
    for n in (1, 100, 10_000):
        for steps in (25, 1000):
            print(f"{n:>6} {steps:>5} " + " ".join(f"{rate(e, n, steps):>16,.0f}" for e in engines_order))
    print()
    for k, v in ratios.items():
        print(
            f"{k:<45} {v:6.2f}  "
            + (
                "(no target: the hard ceiling)"
                if targets[k] is None
                else f"(target >= {targets[k]:g}: {'met' if v >= targets[k] else 'NOT met'})"
            )
        )
    print(f"\nper CPU-second (ceiling {cpu_ceiling_steps:,.0f} steps per CPU-s):")
    print(f"{'N':>6} {'T':>5} " + " ".join(f"{e:>16.16}" for e in engines_order))
    for n in (1, 100, 10_000):
        for steps in (25, 1000):
            print(
                f"{n:>6} {steps:>5} "
                + " ".join(f"{rate(e, n, steps, 'steps_per_cpu_s'):>16,.0f}" for e in engines_order)
            )
    for k, v in cpu_ratios.items():
        print(f"{k:<45} {v:6.2f}  (target >= {targets[k]:g}: {'met' if v >= targets[k] else 'NOT met'})")

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "model": "20-256-256-1 tanh, lane-keeping x=30",
                "flop_per_step": FLOP_PER_STEP,
                "native_variant": native.variant(),
                "threads": THREADS,
                "cpu": platform.processor() or platform.machine(),
                "cores": os.cpu_count(),
                "ceiling": {**ceiling, "steps_per_s": ceiling_steps},
                "ceilings": ceilings,
                "peak_flops": peak,
                "peak_steps_per_s": peak / FLOP_PER_STEP,
                "results": rows,
                "ratios": ratios,
                "ratios_per_cpu_s": cpu_ratios,
                "ceiling_steps_per_cpu_s": cpu_ceiling_steps,
                "targets": targets,
                "quick": args.quick,
            },
            indent=1,
        )
        + "\n"
    )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

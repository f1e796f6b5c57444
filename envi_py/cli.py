"""``envi``: the command line. Each subcommand reads files, calls the library and writes files.

Data flows one way: ``split`` (which logs train, validate, test) -> ``train`` -> ``simulate`` ->
``verify``; ``demo`` chains them on the project's own twin data. Bad input ends with exit code 2
and a one-line reason; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from .controllers import ControllerSpec, parse_params
from .dataset import EXTRA_CHANNELS
from .logs import DatasetSpec, Log, LogError, load_logs, write_log
from .metrics import MetricConfig

#: Subcommands contributed by other parts of the project: "module:function" taking the subparsers.
PLUGINS: tuple[str, ...] = (
    "envi_py.twin.cli:register",
    "envi_py.experiments.cli:register",
    "envi_py.diagnose.cli:register",
    "firmware_bridge.host.brick_sim:register",
)


def parse_where(items: Sequence[str] | None) -> dict[str, list[Any]] | None:
    """``["x=10,30,50"]`` -> ``{"x": [10, 30, 50]}``."""
    if not items:
        return None
    out: dict[str, list[Any]] = {}
    for item in items:
        key, sep, values = item.partition("=")
        if not sep:
            raise ValueError(f"--where {item!r}: expected name=value[,value...]")
        out[key] = [float(v) if v.replace(".", "", 1).lstrip("-").isdigit() else v for v in values.split(",")]
    return out


def add_log_args(p: argparse.ArgumentParser, flag: str = "--logs", required: bool = True, help: str = "") -> None:
    dest = flag.lstrip("-").replace("-", "_")
    p.add_argument(flag, dest=dest, nargs="+", required=required,
                   help=help or "log files, folders or manifest .json files (sorted, validated)")
    p.add_argument("--pattern", default=None,
                   help="file name pattern for logs without sidecar, e.g. 'log_{x}_{run}.csv' "
                        "(fields become controller parameters; 'run' the run id)")
    p.add_argument("--controller-name", default="lane-keeping",
                   help="controller that produced logs without sidecar (default lane-keeping)")
    p.add_argument("--where", nargs="*", default=None, help="keep logs whose parameters match, e.g. x=10,30,50")
    p.add_argument("--skip-bad", action="store_true", help="skip (with a warning) logs that fail validation")


def read_logs(args: argparse.Namespace, attr: str = "logs", min_length: int = 1) -> list[Log]:
    spec = DatasetSpec(pattern=args.pattern, controller=args.controller_name)
    return load_logs(getattr(args, attr), spec, min_length=min_length, skip_bad=args.skip_bad,
                     where=parse_where(args.where))


def add_metric_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--centre", type=float, default=40.0, help="lane centre in colour units (default 40)")
    p.add_argument("--band", type=float, default=10.0, help="half-width of the steady band (default 10)")


def metric_config(args: argparse.Namespace, skip: int) -> MetricConfig:
    return MetricConfig(centre=args.centre, band=args.band, skip=skip)


def write_manifest(path: Path, logs: Sequence[Log], args: argparse.Namespace) -> None:
    manifest = {"controller": args.controller_name, "logs": [str(Path(lg.path).resolve()) for lg in logs if lg.path]}
    if args.pattern:
        manifest["pattern"] = args.pattern
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(manifest, indent=1) + "\n")


# ------------------------------------------------------------------------------------ split

def cmd_split(args: argparse.Namespace) -> int:
    """Choose disjoint train / validation / test logs (whole logs, seeded) and write three manifests."""
    import numpy as np

    logs = read_logs(args)
    want = {"test": args.test, "val": args.val, "train": args.train}
    fixed = sum(v for v in want.values() if v is not None)
    if fixed > len(logs):
        raise ValueError(f"asked for {fixed} logs but only {len(logs)} match")
    if args.mode == "blocks":
        order = np.arange(len(logs))  # natural order: test from the end, train from the start
        test_idx = order[len(logs) - (args.test or 0):]
        rest = order[: len(logs) - (args.test or 0)]
    else:
        order = np.random.default_rng(args.seed).permutation(len(logs))
        test_idx, rest = order[: args.test or 0], order[args.test or 0:]
    val_idx = rest[len(rest) - (args.val or 0):]
    rest = rest[: len(rest) - (args.val or 0)]
    train_idx = rest if args.train is None else rest[: args.train]
    out = Path(args.out)
    for name, idx in (("train", train_idx), ("val", val_idx), ("test", test_idx)):
        write_manifest(out / f"{name}.json", [logs[i] for i in sorted(idx)], args)
        print(f"{name}: {len(idx)} logs -> {out / (name + '.json')}")
    return 0


# ------------------------------------------------------------------------------------ train

def cmd_train(args: argparse.Namespace) -> int:
    from .train import train

    logs = read_logs(args, min_length=args.history + 1)
    val = read_logs(args, "val_logs", min_length=args.history + 1) if args.val_logs else []
    kwargs: dict[str, Any] = {"seed": args.seed, "history": args.history, "progress": not args.quiet,
                              "metric": metric_config(args, args.history)}
    if args.algorithm != "random":
        kwargs.update(epochs=args.epochs, hidden=[int(h) for h in args.hidden.split(",") if h],
                      head=args.head, eval_every=args.eval_every, extras=tuple(args.extras),
                      play_width=args.play_width, context=args.context)
        if args.lr is not None:
            kwargs["lr"] = args.lr
    t0 = time.perf_counter()
    ckpt = train(args.algorithm, logs, val, **kwargs)
    path = ckpt.save(args.output)
    sel = ckpt.record.selection
    print(f"trained {args.algorithm} on {len(logs)} logs ({len(val)} validation) in "
          f"{time.perf_counter() - t0:.1f} s; selected epoch {sel.get('best_epoch', '-')}; saved {path}")
    return 0


# ------------------------------------------------------------------------------------ simulate

def cmd_simulate(args: argparse.Namespace) -> int:
    from .model import Checkpoint
    from .simulate import choose_engine, simulate_logs
    from .verify import controller_of, group_by_controller

    ckpt = Checkpoint.load(args.model)
    init = read_logs(args, "init_logs", min_length=ckpt.config.history)
    out = Path(args.out)
    if args.controller:
        groups = {"given": (ControllerSpec(args.controller, parse_params(args.param)), init)}
    else:
        groups = {k: (controller_of(g[0]), g) for k, g in group_by_controller(init).items()}
    n = 0
    t0 = time.perf_counter()
    engines = set()
    for spec, logs in groups.values():
        engines.add(choose_engine(ckpt, spec, args.engine))
        for lg in simulate_logs(ckpt, spec, logs, steps=args.steps, runs=args.runs, seed=args.seed,
                                engine=args.engine):
            write_log(lg, out / f"{lg.meta.run_id}.csv")
            n += 1
    print(f"simulated {n} runs in {time.perf_counter() - t0:.2f} s ({'+'.join(sorted(engines))} engine) -> {out}")
    return 0


# ------------------------------------------------------------------------------------ verify

def cmd_verify(args: argparse.Namespace) -> int:
    from .verify import to_text, verify, write_report

    real = read_logs(args, "real")
    sim = load_logs(args.sim, skip_bad=args.skip_bad)
    results = verify(real, sim, metric_config(args, args.skip), floor_splits=args.floor_splits, seed=args.seed)
    print(to_text(results))
    if args.out:
        md, js = write_report(results, Path(args.out))
        print(f"report: {md} {js}")
    return 0


# ------------------------------------------------------------------------------------ demo

def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the project's own data: twin logs -> split -> BC -> simulate -> verify."""
    from .demo import run_demo

    run_demo(Path(args.out), seed=args.seed, epochs=args.epochs)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="envi", description="Learn an environment model from field logs "
                                     "and verify a controller against it.")
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("split", help="choose train/validation/test logs; writes train.json, val.json, test.json")
    add_log_args(p)
    p.add_argument("--train", type=int, default=None, help="number of training logs (default: all the rest)")
    p.add_argument("--val", type=int, default=0, help="number of validation logs (model selection)")
    p.add_argument("--test", type=int, default=0, help="number of test logs (verification)")
    p.add_argument("--mode", choices=("random", "blocks"), default="random",
                   help="random: seeded draw; blocks: test logs are the last ones in file order (the real "
                        "logs are consecutive slices of one run, so blocks keeps neighbours apart)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True, help="folder for the three manifests")
    p.set_defaults(func=cmd_split)

    p = sub.add_parser("train", help="train an environment model")
    add_log_args(p, help="training logs")
    p.add_argument("--val-logs", nargs="*", default=None, help="validation logs for closed-loop model selection")
    p.add_argument("--algorithm", choices=("bc", "gail", "bcxgail", "random"), default="bc")
    p.add_argument("--epochs", type=int, default=300)
    p.add_argument("--lr", type=float, default=None, help="learning rate (default: the algorithm's, BC 5e-5)")
    p.add_argument("--history", type=int, default=10, help="window length l")
    p.add_argument("--hidden", default="256,256", help="hidden widths")
    p.add_argument("--head", choices=("deterministic", "gaussian"), default="deterministic")
    p.add_argument("--extras", nargs="*", choices=EXTRA_CHANNELS, default=[],
                   help="derived input channels (what a diagnosis' fix may add): dt, phase, play")
    p.add_argument("--play-width", type=float, default=0.0,
                   help="the play channel's full width, a fraction of the action range")
    p.add_argument("--context", action="store_true", help="append the per-run context of the initial window")
    p.add_argument("--eval-every", type=int, default=10, help="epochs between closed-loop validations")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_metric_args(p)
    p.add_argument("-o", "--output", required=True, help="checkpoint file to write")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("simulate", help="simulate a controller against a model from real initial windows")
    p.add_argument("--model", required=True)
    add_log_args(p, "--init-logs", help="logs whose first l rows start the simulations")
    p.add_argument("--controller", default=None,
                   help="controller name or package.module:function (default: each log's own controller)")
    p.add_argument("--param", nargs="*", default=None, help="controller parameters, e.g. x=30")
    p.add_argument("--runs", type=int, default=1, help="runs per initial window")
    p.add_argument("--steps", type=int, default=None, help="steps after the window (default: the log's length)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--engine", choices=("auto", "native", "torch"), default="auto",
                   help="auto (default): the C++ engine when it can run the model, else PyTorch")
    p.add_argument("--out", required=True, help="folder for simulated logs")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("verify", help="compare real and simulated logs: accuracy, distances, floor")
    add_log_args(p, "--real", help="real logs")
    p.add_argument("--sim", nargs="+", required=True, help="simulated logs (with sidecars)")
    add_metric_args(p)
    p.add_argument("--skip", type=int, default=10, help="leading rows not scored (the initial window)")
    p.add_argument("--floor-splits", type=int, default=20, help="random halvings for the real-vs-real floor")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="folder for report.md and report.json")
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser("demo", help="the main job on the built-in twin data")
    p.add_argument("--out", default="demo_out")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--epochs", type=int, default=300)
    p.set_defaults(func=cmd_demo)

    for plugin in PLUGINS:
        module, _, fn = plugin.partition(":")
        getattr(importlib.import_module(module), fn)(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except (LogError, ValueError, OSError, KeyError) as exc:
        if args.debug:
            raise
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"envi {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"envi {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

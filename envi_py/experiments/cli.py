"""``envi experiment {tovk,tmvk,tmvu}``: the paper's use cases on a folder of logs."""

from __future__ import annotations

import argparse
from typing import Any

from ..cli_parser import seed_type
from ..files import output_folder


def _cmd(args: argparse.Namespace) -> int:
    from ..cli import _at_most, _positive, read_logs, system_of
    from ..executor import make_executor
    from .run import run_experiment
    from .versions import VersionChoice

    # before any log is read or job started (--reps 0 once finished 'successfully' doing nothing)
    _positive(args, "reps", "epochs", "history", "runs")
    _at_most(args, reps=10_000, epochs=1_000_000, history=10_000, runs=1_000_000)
    if min(args.n) < 1 or args.n_val < 0:
        raise ValueError(f"--n must be at least 1 and --n-val at least 0, got --n {args.n} --n-val {args.n_val}")
    if args.workers is not None and args.workers < 0:  # 0: in this process
        raise ValueError(f"--workers must be at least 0 (0: in this process), got {args.workers}")
    if args.n_test < 2:  # the grid's split needs two (once blamed on the number of logs)
        raise ValueError(f"--n-test must be at least 2 (test logs per version), got {args.n_test}")
    output_folder(args.out)
    logs = read_logs(args, min_length=args.history + 1)
    versions = VersionChoice(
        tuple(args.train_versions or ()),
        tuple(args.eval_versions or ()),
        tuple(args.unseen_versions or ()),
        args.tovk_version,
    )
    executor = make_executor(args.dask, args.workers)
    try:
        res = run_experiment(
            logs,
            args.use_cases,
            args.out,
            algorithms=args.algorithms,
            ns=args.n,
            reps=args.reps,
            seed=args.seed,
            protocol=args.protocol,
            epochs=args.epochs,
            n_val=args.n_val,
            n_test=args.n_test,
            runs=args.runs,
            executor=executor,
            progress=not args.quiet,
            train_kwargs={"history": args.history},
            resume=not args.fresh,
            system=system_of(args),
            versions=versions,
        )
    finally:
        executor.close()
    print(f"{res['meta']['jobs']} trainings in {res['meta']['wall_seconds']:.0f} s; report: {res['report']}")
    return 0


def register(sub: Any) -> None:
    """Add ``experiment`` to the ``envi`` subcommands."""
    from ..cli import add_log_args

    p = sub.add_parser(
        "experiment",
        help="the paper's use cases (TOVK, TMVK, TMVU): train every algorithm "
        "for several n and seeds, verify, tabulate",
    )
    p.add_argument(
        "use_cases",
        nargs="+",
        choices=("tovk", "tmvk", "tmvu"),
        help="one or more; tmvk and tmvu share their trainings when given together",
    )
    add_log_args(p, "--logs", required=True)
    version = "name=value[,name=value] as the report labels versions, e.g. x=30 or kp_steer=0.8,kp_speed=18"
    p.add_argument(
        "--train-versions",
        nargs="+",
        metavar="VERSION",
        help=f"versions TMVK and TMVU train on, each {version} (default for lane keeping: x=10 x=30 x=50)",
    )
    p.add_argument(
        "--eval-versions",
        nargs="+",
        metavar="VERSION",
        help="trained versions TMVK verifies (default: every trained one)",
    )
    p.add_argument(
        "--unseen-versions",
        nargs="+",
        metavar="VERSION",
        help="versions TMVU verifies, never trained on (default for lane keeping: x=20 x=40)",
    )
    p.add_argument(
        "--tovk-version",
        metavar="VERSION",
        help="the one version TOVK trains on and verifies (default for lane keeping: x=30)",
    )
    p.add_argument(
        "--algorithms",
        nargs="+",
        default=["random", "bc", "gail", "bcxgail"],
        choices=("random", "bc", "gail", "bcxgail"),
    )
    p.add_argument("--n", nargs="+", type=int, default=[3, 15, 30], help="training logs per version")
    p.add_argument("--reps", type=int, default=5, help="repetitions (seeds and log draws)")
    p.add_argument("--epochs", type=int, default=300)
    p.add_argument("--history", type=int, default=10)
    p.add_argument("--n-val", type=int, default=3, help="validation logs per version (model selection)")
    p.add_argument("--n-test", type=int, default=30, help="test logs per version (at most)")
    p.add_argument("--runs", type=int, default=1, help="simulated runs per test log's initial window")
    p.add_argument(
        "--protocol",
        choices=("random", "authors"),
        default="random",
        help="'authors': their sorted-order 5-fold split (first n train, last 10 test)",
    )
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument(
        "--workers", type=int, default=None, help="local worker processes (default: all cores; 0: in this process)"
    )
    p.add_argument("--dask", default=None, metavar="ADDRESS", help="run on a Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--fresh",
        action="store_true",
        help="retrain every job (default: reuse finished jobs recorded in the output folder); the earlier "
        "journal is replaced only when the fresh run completes",
    )
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--out", default="experiment", help="output folder")
    p.set_defaults(func=_cmd)

"""``envi diagnose``: the diagnosis of a model against real logs."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def _cmd_diagnose(args: argparse.Namespace) -> int:
    from ..cli import metric_config, read_logs
    from ..model import Checkpoint
    from .report import write_diagnosis
    from .run import diagnose

    ckpt = Checkpoint.load(args.model)
    hist = ckpt.config.history
    real = read_logs(args, "real", min_length=hist + 1)
    confirm = read_logs(args, "confirm", min_length=hist + 1) if args.confirm else None
    train_logs = read_logs(args, "train_logs", min_length=hist + 1) if args.train_logs else None
    d = diagnose(ckpt, real, confirm, train_logs, metric=metric_config(args, hist), runs=args.runs,
                 top=args.top, retrain=not args.no_retrain, seed=args.seed)
    md = write_diagnosis(d, Path(args.out))
    print(d.verdict())
    print(f"report: {md}")
    return 0


def register(sub: Any) -> None:
    """Add ``diagnose`` to the ``envi`` subcommands."""
    from ..cli import add_log_args, add_metric_args

    p = sub.add_parser("diagnose", help="where the sim-to-real gap lies, which effect causes it, "
                                        "how far it shrinks once added")
    add_log_args(p, "--real", help="real logs to diagnose against (choose + confirm)")
    p.add_argument("--model", required=True, help="checkpoint to diagnose")
    p.add_argument("--confirm", nargs="*", default=None,
                   help="confirmation logs, used neither for training nor for choosing the effect "
                        "(default: half of --real, per controller version)")
    p.add_argument("--train-logs", nargs="*", default=None,
                   help="the model's training logs, if they are not where its checkpoint recorded them")
    p.add_argument("--runs", type=int, default=10, help="simulated runs per initial window")
    p.add_argument("--top", type=int, default=2, help="how many significant effects to retrain with")
    p.add_argument("--no-retrain", action="store_true", help="skip the retraining (step 3)")
    p.add_argument("--seed", type=int, default=0)
    add_metric_args(p)
    p.add_argument("--out", default="diagnosis", help="output folder")
    p.set_defaults(func=_cmd_diagnose)

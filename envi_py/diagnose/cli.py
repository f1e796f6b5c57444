"""``envi diagnose``: the diagnosis of a model against real logs."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ..atomic import atomic_write_text
from ..cli_parser import seed_type
from ..files import output_folder


#: simulated runs per initial window at most: a diagnosis holds every run's trace in memory
MAX_RUNS_PER_WINDOW = 10_000


def runs_fit_in_memory(runs: int) -> None:
    """``--runs`` refused above :data:`MAX_RUNS_PER_WINDOW` (10^8 once ran into a MemoryError after
    the first stage)."""
    if runs > MAX_RUNS_PER_WINDOW:
        raise ValueError(f"--runs {runs}: at most {MAX_RUNS_PER_WINDOW:,} simulated runs per initial window")


def _cmd_diagnose(args: argparse.Namespace) -> int:
    from ..cli import read_logs
    from ..logs import Log, logs_fit_model
    from ..model import Checkpoint
    from .layers import layers_path
    from .report import kept_model_name, layer_shown_to_help, write_diagnosis
    from .run import diagnose

    if not args.model or not args.real:
        args.parser.error("envi diagnose needs --model and --real (or the 'validate' mode)")
    # sizes and the output before any work (--runs 0 once 'min() arg is an empty sequence' after a stage)
    if args.runs < 1 or args.top < 1:
        raise ValueError(f"--runs and --top must be at least 1, got {args.runs} and {args.top}")
    runs_fit_in_memory(args.runs)
    output_folder(args.out)
    ckpt = Checkpoint.load(args.model)
    hist = ckpt.config.history

    def model_logs(attr: str) -> list[Log]:
        return logs_fit_model(
            read_logs(args, attr, min_length=hist + 1), ckpt.schema, args.model, ckpt.record.period_ms
        )

    real = model_logs("real")
    confirm = model_logs("confirm") if args.confirm else None
    shared = {lg.sha256() for lg in real} & {lg.sha256() for lg in confirm or []}
    if shared:  # confirmation logs that also chose the effect confirm nothing
        raise ValueError(
            f"--confirm: {len(shared)} of its logs are also among --real; confirmation logs must be others"
        )
    train_logs = model_logs("train_logs") if args.train_logs else None
    val_logs = model_logs("val_logs") if args.val_logs else None
    kept: dict[str, Checkpoint] = {}
    d = diagnose(
        ckpt,
        real,
        confirm,
        train_logs,
        val_logs,
        runs=args.runs,
        top=args.top,
        retrain=not args.no_retrain,
        seed=args.seed,
        refit=not args.no_refit,
        keep_models=kept,
        progress=None if args.quiet else lambda text: print(f"[diagnose] {text}", file=sys.stderr, flush=True),
    )
    out, model = Path(args.out), Path(args.model)
    files = write_diagnosis(d, out, model=model, kept=kept)
    print(d.verdict())
    print(f"report: {files.html} {files.markdown}")
    for effect in kept:
        print(f"model with {effect}: {out / kept_model_name(model, effect)}")
    if layer_shown_to_help(d):
        path = layers_path(out / model.name)
        print(f"fitted layer: {path} (simulate it: envi simulate --model {args.model} --layers {path} ...)")
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from .validate import ALL_CASES, Size, cross_table, layer_table, run_validation, score, to_markdown

    # sizes before any trial (--runs 0 once ran the whole study into a timeout)
    for name in ("seeds", "jobs", "train", "diag", "steps", "epochs", "history", "runs"):
        if getattr(args, name) < 1:
            raise ValueError(f"--{name} must be at least 1, got {getattr(args, name)}")
    runs_fit_in_memory(args.runs)
    if args.steps <= args.history:  # every trial once failed on its logs and the report read 'nan%'
        raise ValueError(f"--steps {args.steps}: logs must be longer than the model's --history {args.history}")
    if args.diag < 2:  # half choose the effect, half confirm it
        raise ValueError(f"--diag {args.diag}: at least 2 logs, half to choose the effect and half to confirm it")
    for name in ("shrink_seeds", "val", "first_seed"):
        if getattr(args, name) < 0:
            raise ValueError(f"--{name.replace('_', '-')} must be at least 0, got {getattr(args, name)}")
    if not 0 < args.lr < 1e3:
        raise ValueError(f"--lr must be a positive learning rate below 1000, got {args.lr}")
    worlds = list(dict.fromkeys(args.world))
    procedures = list(dict.fromkeys(args.procedure))
    known = {c.name: c for c in ALL_CASES}
    unknown = set(args.cases or ()) - set(known)
    if unknown:
        raise ValueError(f"unknown case(s) {', '.join(sorted(unknown))}; known: {', '.join(known)}")
    cases = [known[n] for n in args.cases] if args.cases else list(ALL_CASES)
    size = Size(
        train=args.train,
        val=args.val,
        diagnose=args.diag,
        steps=args.steps,
        epochs=args.epochs,
        lr=args.lr,
        history=args.history,
        runs=args.runs,
    )
    out = Path(args.out)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    results = run_validation(out, cases, seeds, args.mode, size, args.shrink_seeds, args.jobs, worlds, procedures)
    scores = [score(results, m, w, pr) for pr in procedures for w in worlds for m in args.mode]
    md = to_markdown(scores, size)
    if len(worlds) > 1 or len(procedures) > 1:
        md = cross_table(results, args.mode, worlds, procedures) + "\n\n" + md
    else:
        md += "\n".join(layer_table(results, worlds, procedures))
    atomic_write_text(out / "report.md", md + "\n")
    atomic_write_text(out / "scores.json", json.dumps([asdict(s) for s in scores], indent=1) + "\n")
    print(md)
    print(f"report: {out / 'report.md'}")
    return 0


def register(sub: Any) -> None:
    """Add ``diagnose`` to the ``envi`` subcommands."""
    from ..cli import add_log_args

    p = sub.add_parser(
        "diagnose",
        help="where the sim-to-real gap lies, which effect causes it, how far it shrinks once added "
        "(gaps on the goals of the model's system description: its preset's and its declared ones)",
    )
    add_log_args(p, "--real", required=False, help="real logs to diagnose against (choose + confirm)")
    p.add_argument("--model", help="checkpoint to diagnose")
    p.add_argument(
        "--confirm",
        nargs="*",
        default=None,
        help="confirmation logs, used neither for training nor for choosing the effect "
        "(default: half of --real, per controller version)",
    )
    p.add_argument(
        "--train-logs",
        nargs="*",
        default=None,
        help="the model's training logs, if they are not where its checkpoint recorded them",
    )
    p.add_argument(
        "--val-logs",
        nargs="*",
        default=None,
        help="the model's validation logs, if they are not where its checkpoint recorded them",
    )
    p.add_argument("--runs", type=int, default=10, help="simulated runs per initial window")
    p.add_argument("--top", type=int, default=2, help="how many significant effects to retrain with")
    p.add_argument("--no-retrain", action="store_true", help="skip the retraining with the effects found (step 6)")
    p.add_argument(
        "--no-refit",
        action="store_true",
        help="a deterministic model whose runs vary far less than the real ones is diagnosed as it is, "
        "not refitted with a Gaussian head first",
    )
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument(
        "--out",
        default="diagnosis",
        help="output folder; an earlier diagnosis there is replaced as a whole (its report, figures, kept "
        "models and fitted layer; other files are left alone)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on standard error")
    p.set_defaults(func=_cmd_diagnose, parser=p)

    from .size import PROCEDURES, TUNED_ON, WORLDS, Size, default_jobs

    modes = p.add_subparsers(dest="diagnose_mode", metavar="validate")
    v = modes.add_parser("validate", help="score the diagnosis on twin data whose effect is known and withheld")
    d = Size()
    v.add_argument(
        "--cases", nargs="*", default=None, help="validation cases (default: all, incl. the negative controls)"
    )
    v.add_argument(
        "--world",
        nargs="+",
        choices=WORLDS,
        default=[TUNED_ON],
        help="world families: steered (the line follower every threshold was chosen on), diffdrive (a "
        "differential-drive robot on a curved track, never used to choose a threshold, though the jitter, noise, "
        "backlash and held-out share rules were read off it); two print the cross-world table",
    )
    v.add_argument(
        "--procedure",
        nargs="+",
        choices=PROCEDURES,
        default=[PROCEDURES[0]],
        help="shipped (default): models trained with envi train's defaults and diagnosed in stages, as a user "
        "gets them; as-tuned: as the rules were chosen (output neither rounded nor clamped, no Gaussian refit); "
        "two print them side by side",
    )
    v.add_argument("--seeds", type=int, default=20, help="seeds per case (default 20)")
    v.add_argument("--first-seed", type=seed_type, default=0)
    v.add_argument(
        "--mode",
        nargs="+",
        choices=("withheld", "verification"),
        default=["withheld", "verification"],
        help="withheld: effect in all logs, missing from the model; verification: effect only in "
        "the logs verified against",
    )
    v.add_argument("--shrink-seeds", type=int, default=5, help="seeds per case that also retrain with the fix")
    v.add_argument("--jobs", type=int, default=default_jobs(), help="parallel trials")
    v.add_argument("--train", type=int, default=d.train, help="training logs per trial")
    v.add_argument("--val", type=int, default=d.val, help="validation logs per trial")
    v.add_argument("--diag", type=int, default=d.diagnose, help="logs diagnosed per trial (half choose, half confirm)")
    v.add_argument("--steps", type=int, default=d.steps, help="rows per log")
    v.add_argument("--epochs", type=int, default=d.epochs)
    v.add_argument("--lr", type=float, default=d.lr)
    v.add_argument("--history", type=int, default=d.history, help="model history (cases that set their own keep it)")
    v.add_argument("--runs", type=int, default=d.runs, help="simulated runs per initial window")
    v.add_argument("--out", default="diagnosis-validation", help="output folder (results.jsonl resumes)")
    v.set_defaults(func=_cmd_validate)

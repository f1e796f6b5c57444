"""``envi twin generate [--system car] | effects | calibrate``; hooked into ``envi`` by :func:`register`."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Callable

from envi_py.cli_parser import seed_type
from envi_py.controllers import ControllerSpec, parse_params
from envi_py.files import output_folder, plain_tree, read_text
from envi_py.logs import group_by_param, load_logs, refuse_earlier_logs, remove_logs
from envi_py.notes import one_line
from envi_py.system import lane_keeping, load_system

from .car import generate_car, generate_car_versions, write_car_logs
from .diffdrive import DIFFDRIVE_EFFECTS, generate_diffdrive
from .effects import describe, parse_effects
from .generate import generate, write_logs
from .profile import TwinProfile, default_profile


#: The most samples (runs x steps) one ``generate`` writes: beyond it the arrays do not fit in memory
#: and numpy fails with a MemoryError traceback (or the system's OOM killer ends the process).
MAX_SAMPLES = 100_000_000


def _profile(args: argparse.Namespace) -> TwinProfile:
    return _load_profile(args.profile) if args.profile else default_profile()


def _load_profile(path: str, option: str = "--profile") -> TwinProfile:
    """A profile JSON, or a ValueError naming the option and the file (not json's bare 'Expecting
    value'); a named pipe or a folder is refused before it is opened (reading a pipe blocks for ever)."""
    try:
        text = read_text(path, "a twin profile")
    except ValueError as exc:
        raise ValueError(f"{option} {exc}") from None
    try:  # a NaN is parsed here and refused by the profile, which names its parameter
        tree = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"{option} {path}: not a twin profile JSON ({exc})") from None
    tree = plain_tree(tree, f"{option} {path}", "a twin profile")
    try:
        return TwinProfile.from_json(tree)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ValueError(f"{option} {path}: not a twin profile JSON ({exc})") from None


def _refusing(sub: str, func: Callable[[argparse.Namespace], int]) -> Callable[[argparse.Namespace], int]:
    """``func`` with every refusal as one line ``envi twin SUB: error: ...`` and exit code 2 (the
    form of argparse's own usage errors for the sub-command); ``--debug`` shows the traceback."""

    def run(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except BrokenPipeError:
            raise  # 'envi twin effects | head': envi's main ends it quietly
        except (ValueError, OSError, KeyError) as exc:  # a LogError is a ValueError
            if getattr(args, "debug", False):
                raise
            msg = one_line(_os_message(exc) if isinstance(exc, OSError) else str(exc)) or type(exc).__name__
            print(f"envi twin {sub}: error: {msg}", file=sys.stderr)
            return 2

    run.__doc__ = func.__doc__
    return run


def _checked(args: argparse.Namespace) -> dict[str, object]:
    """The size, output folder and parameters checked before any work; returns ``--param``'s values
    (a NaN gain once wrote logs full of NaN, a too large size a MemoryError traceback). An output
    folder holding logs of an earlier run is refused without ``--force``: the new logs would mix with
    those the new run does not overwrite."""
    if args.runs < 1 or args.steps < 1:
        raise ValueError(f"--runs and --steps must be at least 1, got {args.runs} and {args.steps}")
    if args.runs * args.steps > MAX_SAMPLES:
        raise ValueError(f"--runs x --steps is at most {MAX_SAMPLES:,} samples, got {args.runs} x {args.steps}")
    out = output_folder(args.out)
    parse_params(args.world, "--world")
    params = parse_params(args.param, "--param")
    refuse_earlier_logs(out, args.force)
    return params


def _write(args: argparse.Namespace, write: Callable[[], list[Path]]) -> tuple[list[Path], str]:
    """``write()`` into ``--out`` after removing its earlier logs when ``--force`` says so (only once
    every check has passed); the paths written and a note of what was replaced."""
    replaced = remove_logs(args.out) if args.force else 0
    return write(), f"; replaced {replaced} earlier logs" if replaced else ""


def _os_message(exc: OSError) -> str:
    """'FILE: reason' for an OSError (its str() is '[Errno 17] File exists: ...')."""
    return f"{exc.filename}: {exc.strerror}" if exc.filename and exc.strerror else str(exc)


def _generate(args: argparse.Namespace) -> int:
    """Either twin family's logs into ``--out``; every refusal is one line and exit code 2."""
    if args.system == "car":
        if args.family != "steered":
            raise ValueError("--family applies to the lane-keeping twin only")
        job = _generate_car
    else:
        if args.version is not None or args.world is not None:
            raise ValueError("--version and --world apply to --system car only")
        job = _generate_lane
    print(job(args))
    return 0


cmd_generate = _refusing("generate", _generate)


def _generate_lane(args: argparse.Namespace) -> str:
    """The lane-keeping twin (steered or diffdrive world); the summary line of what was written."""
    spec = lane_keeping().with_version_defaults(ControllerSpec(args.controller or "lane-keeping", _checked(args)))
    spec.build()  # fail on a bad controller before any work
    diffdrive = args.family == "diffdrive"
    try:  # every parameter finite and in range: a NaN noise once wrote logs all NaN
        effects = parse_effects(args.effects, DIFFDRIVE_EFFECTS if diffdrive else None)
    except ValueError as exc:
        raise ValueError(f"--effects {args.effects}: {exc}") from None
    if diffdrive:
        if args.profile is not None:
            raise ValueError("--profile is the steered world's calibrated profile; the diffdrive world has its own")
        logs = generate_diffdrive(spec, args.runs, args.steps, effects, args.seed)
    else:
        logs = generate(spec, args.runs, args.steps, effects, args.seed, _profile(args))
    paths, note = _write(args, lambda: write_logs(logs, args.out))
    active = ", ".join(logs[0].meta.provenance["effects"]) or "none"
    return f"wrote {len(paths)} {args.family} twin logs to {args.out} (effects: {active}{note})"


def _generate_car(args: argparse.Namespace) -> str:
    """The car twin: the shipped versions (all, or ``--version``), or one controller from
    ``--param kp_steer=.. kp_speed=..`` on the description's controller (or ``--controller``);
    the summary line of what was written."""
    _checked(args)
    if args.effects is not None or args.profile is not None:
        raise ValueError(
            "--effects and --profile apply to the lane-keeping twin; the car's world "
            "takes --world name=value (e.g. dropout_prob=0)"
        )
    twice = sorted({v for v in args.version or () if args.version.count(v) > 1})
    if twice:  # found here, not by the writer after --force has removed the earlier logs
        raise ValueError(f"--version {twice[0]} is given twice: its logs would overwrite each other")
    world = parse_params(args.world, "--world")
    if args.param is not None or args.controller is not None:
        if args.version is not None:
            raise ValueError("give either --version or --param/--controller, not both")
        params = parse_params(args.param, "--param")
        if args.controller:
            spec = ControllerSpec(args.controller, params)
        else:
            car = load_system("car")
            car.check_version_fields(params, f"--param {' '.join(args.param or [])}")
            spec = car.controller_for(params)
        if spec is None:
            raise ValueError("the car system description declares no controller")
        spec.build(n_state=2, n_action=2)  # fail on a bad controller before any work
        logs = generate_car(spec, args.runs, args.steps, args.seed, **world)
    else:
        logs = generate_car_versions(args.runs, args.steps, args.seed, args.version, **world)
    paths, note = _write(args, lambda: write_car_logs(logs, args.out))
    return f"wrote {len(paths)} car twin logs to {args.out} (pattern car_{{kp_steer}}_{{kp_speed}}_{{run}}.csv{note})"


def _effects(args: argparse.Namespace) -> int:
    """The effects table and the profile's effects; the profile is read first, so a bad one prints
    only its one error line."""
    prof = _profile(args)
    print(describe())
    print("\nprofile effects (on by default): " + ", ".join(f"{k}={v}" for k, v in prof.effects.items()))
    return 0


cmd_effects = _refusing("effects", _effects)


def _calibration_logs(args: argparse.Namespace) -> list:
    """``--logs``, ``--key``, ``--budget`` and ``--out`` checked before the long search: a folder of
    logs with at least two runs of each version (the real-vs-real floor splits them in halves)."""
    if not math.isfinite(args.budget) or args.budget <= 0:
        raise ValueError(f"--budget must be a number of seconds above 0, got {args.budget:g}")
    output_folder(args.out)
    logs_dir = Path(args.logs)
    if not logs_dir.is_dir():
        what = "no such folder" if not logs_dir.exists() else "not a folder"
        raise ValueError(f"--logs {logs_dir}: {what}; --logs takes a folder of real logs ({args.pattern})")
    logs = load_logs(logs_dir, lane_keeping().with_pattern(args.pattern))
    known = sorted({k for lg in logs for k in lg.param})
    if args.key not in known:
        raise ValueError(
            f"--key {args.key}: not a parameter of the logs in {logs_dir}; known: {', '.join(known) or 'none'}"
        )
    missing = [lg for lg in logs if args.key not in lg.param]
    if missing:
        raise ValueError(f"--key {args.key}: {missing[0].path} has no such parameter")
    for value, group in group_by_param(logs, args.key).items():
        if len(group) < 2:
            raise ValueError(
                f"--logs {logs_dir}: {args.key}={value} has 1 log; calibration needs 2 or more runs of each version"
            )
    return logs


def _calibrate(args: argparse.Namespace) -> int:
    from .calibrate import calibrate
    from .report import write_calibration

    logs = _calibration_logs(args)
    budget = 25.0 if args.quick else args.budget
    start = _load_profile(args.start, "--start") if args.start else None
    prof = calibrate(
        logs,
        key=args.key,
        budget_s=budget,
        runs=60 if args.quick else 160,
        seed=args.seed,
        start=start,
        progress=None if args.quiet else print,
    )
    out = Path(args.out)
    prof, _ = write_calibration(prof, logs, out, key=args.key)
    path = out / "profile.json"
    for x, h in prof.fit["headline"].items():
        print(f"{args.key}={x}: {h['within_2x']}/8 metrics within 2x floor, median W1 ratio {h['median_w1_ratio']:.2f}")
    print(f"profile: {path}\nreport: {out / 'report.md'} {out / 'report.json'} {out / 'traces.png'}")
    return 0


cmd_calibrate = _refusing("calibrate", _calibrate)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``twin`` with its sub-commands to the ``envi`` parser."""
    twin = subparsers.add_parser("twin", help="physics twin: generate logs, list effects, calibrate to real logs")
    sub = twin.add_subparsers(dest="twin_command", required=True)

    p = sub.add_parser("generate", help="write twin logs with sidecars")
    p.add_argument(
        "--system",
        choices=("lane-keeping", "car"),
        default="lane-keeping",
        help="which twin: the lane-keeping robot (default) or the car following a lead vehicle",
    )
    p.add_argument(
        "--family",
        choices=("steered", "diffdrive"),
        default="steered",
        help="lane-keeping world family: steered (the calibrated steered vehicle on a straight edge, default) "
        "or diffdrive (a differential-drive robot on a curved track: the diagnosis's cross-world check)",
    )
    p.add_argument(
        "--controller",
        default=None,
        help="registered name or package.module:function (default: lane-keeping; for the car, "
        "its description's two PIDs)",
    )
    p.add_argument(
        "--param",
        nargs="*",
        default=None,
        help="controller parameters, e.g. x=30; for the car its version gains kp_steer=1.2 kp_speed=22",
    )
    p.add_argument(
        "--version",
        nargs="*",
        type=int,
        default=None,
        help="car: shipped versions by index (default: all five; 0-2 train, 3-4 unseen)",
    )
    p.add_argument(
        "--world",
        nargs="*",
        default=None,
        help="car: world parameters, e.g. dropout_prob=0 far_start_prob=0.5 (see CarProfile)",
    )
    p.add_argument("--runs", type=int, default=30)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument(
        "--effects",
        default=None,
        help="on top of the profile's: delay=2,noise=1.5,jitter.pause_prob=0.01,glitch; =0 turns one off",
    )
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument("--profile", default=None, help="profile JSON (default: the shipped calibrated one)")
    p.add_argument(
        "--out",
        required=True,
        help="folder for the logs (CSV with .meta.json sidecars); refused when it already holds logs",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the logs --out already holds: its CSV files and .meta.json sidecars are deleted "
        "before writing (any other file stays), so the folder holds exactly this run",
    )
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("effects", help="list the effects, their parameters and units")
    p.add_argument("--profile", default=None)
    p.set_defaults(func=cmd_effects)

    p = sub.add_parser("calibrate", help="fit a profile to real logs; writes profile.json and a report")
    p.add_argument("--logs", required=True, help="folder of real logs")
    p.add_argument("--pattern", default="log_{x}_{run}.csv")
    p.add_argument("--key", default="x", help="controller parameter that tells the versions apart")
    p.add_argument("--budget", type=float, default=420.0, help="search time in seconds (above 0)")
    p.add_argument("--quick", action="store_true", help="a 25 s search (for tests and smoke runs)")
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument("--start", default=None, help="profile JSON to start the search from (e.g. the shipped one)")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_calibrate)

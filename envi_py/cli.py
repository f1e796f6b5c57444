"""``envi``: the command line. Each subcommand reads files, calls the library and writes files.

Data flows one way: ``split`` (which logs train, validate, test) -> ``train`` -> ``simulate`` ->
``verify``; ``demo`` chains them on the project's own twin data. Bad input ends with exit code 2
and a one-line reason; ``--debug`` shows the traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

from firmware_bridge.host.brick_sim import register as register_brick_sim

from .atomic import atomic_write_text
from .cli_parser import EnviParser, seed_type
from .controllers import ControllerSpec, finite_numbers, parse_params
from .dataset import EXTRA_CHANNELS
from .interrupt import Terminated, exit_code, signals_interrupt
from .notes import held_notes, note, one_line, release
from .files import output_folder, refuse_overwriting, refuse_writing_among_logs, writable_file
from .diagnose.cli import register as register_diagnose
from .experiments.cli import register as register_experiment
from .logs import (
    SIMULATED_SOURCES,
    Log,
    LogError,
    load_logs,
    sidecar_path,
    refuse_earlier_logs,
    staged_logs,
    logs_fit_model,
    write_log,
    write_manifest,
)
from .system import (
    LR_SCHEDULES,
    MAX_MEMBERS,
    STEP_NOISES,
    SystemDescription,
    check_hidden,
    describe_schema,
    load_system,
)
from .twin.cli import register as register_twin

if TYPE_CHECKING:  # torch is imported only once a command needs a model
    from .model import Checkpoint


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
    p.add_argument(
        flag,
        dest=dest,
        nargs="+",
        required=required,
        help=help or "log files, folders or manifest .json files (sorted, validated)",
    )
    p.add_argument(
        "--system",
        default=None,
        metavar="NAME|FILE",
        help="system description (TOML, or a shipped one: lane-keeping, car) for logs without "
        "sidecar; 'envi init --logs DIR' drafts one (default: sidecars, else lane-keeping)",
    )
    p.add_argument(
        "--pattern",
        default=None,
        help="file name pattern for logs without sidecar, e.g. 'log_{x}_{run}.csv' "
        "(fields become controller parameters; 'run' the run id)",
    )
    p.add_argument("--where", nargs="*", default=None, help="keep logs whose parameters match, e.g. x=10,30,50")
    p.add_argument("--skip-bad", action="store_true", help="skip (with a warning) logs that fail validation")


def system_of(args: argparse.Namespace) -> SystemDescription | None:
    """The system description the command line names (with its --pattern), if any."""
    system = load_system(args.system) if getattr(args, "system", None) else None
    if args.pattern:
        system = (system or load_system("lane-keeping")).with_pattern(args.pattern)
    return system


def read_logs(args: argparse.Namespace, attr: str = "logs", min_length: int = 1) -> list[Log]:
    return load_logs(
        getattr(args, attr),
        system_of(args),
        min_length=min_length,
        skip_bad=args.skip_bad,
        where=parse_where(args.where),
    )


def cmd_init(args: argparse.Namespace) -> int:
    """Draft a system description from a folder of logs for the user to edit."""
    from .draft import draft_system

    out = writable_file(args.output, "--output")  # a name that is not text once wrote its draft, then noted it garbled
    if out.exists() and not args.force:
        raise ValueError(f"{out}: exists; choose another --output or pass --force")
    logs = Path(args.logs)
    if logs.is_dir():  # '-o logs/log_30_1.csv --force' once replaced a log with the draft
        refuse_overwriting([out], [p for p in logs.iterdir() if p.name.endswith((".csv", ".meta.json"))], "--output")
    text = draft_system(logs, args.pattern)
    atomic_write_text(out, text)
    system = SystemDescription.load(out)  # what was drafted must read back
    print(f"drafted {out}: check each signal's role, range and resolution, the controller and the goals")
    try:  # the guessed controller must take the file names' fields, or training fails only once it is done
        first = load_logs(sorted(p for p in Path(args.logs).glob("*.csv") if not p.name.startswith("."))[:1], system)
        if first and first[0].meta.controller:
            ControllerSpec.from_json(first[0].meta.controller).build()
    except ValueError as exc:
        note(
            f"envi init: note: {out}: {exc}; name the [controller] and the pattern's fields after its parameters "
            "before training"
        )
    return 0


# ------------------------------------------------------------------------------------ split


def _take(
    group: list[Log], n_train: int | None, n_val: int, n_test: int, mode: str, rng: Any
) -> tuple[list[Log], list[Log], list[Log]]:
    """train / val / test of one set of logs: ``blocks`` keeps file order (test from the end,
    validation before it, training from the start), ``random`` draws them."""
    order = list(range(len(group))) if mode == "blocks" else [int(i) for i in rng.permutation(len(group))]
    if mode == "blocks":
        test, rest = order[len(order) - n_test :] if n_test else [], order[: len(order) - n_test]
    else:
        test, rest = order[:n_test], order[n_test:]
    val, rest = (rest[len(rest) - n_val :], rest[: len(rest) - n_val]) if n_val else ([], rest)
    train = rest if n_train is None else rest[:n_train]
    return ([group[i] for i in sorted(train)], [group[i] for i in sorted(val)], [group[i] for i in sorted(test)])


def cmd_split(args: argparse.Namespace) -> int:
    """Choose disjoint train / validation / test logs (whole logs, seeded) and write three manifests.

    The counts are per controller version (each version keeps its own blocks apart), or totals
    over all matched logs with ``--total``."""
    import numpy as np

    from .logs import group_by_controller

    for flag in ("train", "val", "test"):
        v = getattr(args, flag)
        if v is not None and v < 0:
            raise ValueError(f"--{flag} must not be negative, got {v}")
    out = output_folder(args.out)
    logs = read_logs(args)
    rng = np.random.default_rng(args.seed)
    groups = {"all logs": logs} if args.total else {k.label(): g for k, g in group_by_controller(logs).items()}
    parts: dict[str, list[Log]] = {"train": [], "val": [], "test": []}
    for label, group in groups.items():
        fixed = sum(v for v in (args.train, args.val, args.test) if v is not None)
        if fixed > len(group):
            raise ValueError(f"{label}: asked for {fixed} logs but only {len(group)} match")
        for name, part in zip(("train", "val", "test"), _take(group, args.train, args.val, args.test, args.mode, rng)):
            parts[name] += part
    if not parts["train"]:
        raise ValueError("the split leaves no training logs")
    system = system_of(args)
    for name in parts:  # all three or none: a folder in the way of the last once left a mix of two splits
        target = out / f"{name}.json"
        if target.exists() and not target.is_file():
            raise ValueError(f"{target}: exists and is not a file; nothing written")
    inputs = [q for lg in logs if lg.path for q in (lg.path, sidecar_path(lg.path))]
    inputs += [src for src in args.logs if Path(src).is_file()]  # manifests read
    refuse_overwriting([out / f"{name}.json" for name in parts], inputs, "--out")  # a link to a log, say
    for name, part in parts.items():
        write_manifest(out / f"{name}.json", part, system)
        per = f" ({len(part) // len(groups)} per version)" if len(groups) > 1 and part else ""
        print(f"{name}: {len(part)} logs{per} -> {out / (name + '.json')}")
    return 0


# ------------------------------------------------------------------------------------ train


def state_path(output: Path) -> Path:
    """A training's resumable state: ``<output>.state``, its full name plus a suffix, so two models of
    one stem (``m.pt``, ``m.other``) never share one and an output named ``x.state`` is not its own state."""
    return output.with_name(output.name + ".state")


def _positive(args: argparse.Namespace, *names: str) -> None:
    for name in names:
        v = getattr(args, name)
        if v is not None and v < 1:
            raise ValueError(f"--{name.replace('_', '-')} must be at least 1, got {v}")


def parse_hidden(text: str) -> tuple[int, ...]:
    """``--hidden 128,128`` as widths, checked as the description's ``[training] hidden`` is."""
    try:
        hidden = [int(h) for h in text.split(",")]
    except ValueError:
        raise ValueError(f"--hidden must be comma-separated widths such as 256,256, got {text!r}") from None
    return check_hidden(hidden, "--hidden")


def _at_most(args: argparse.Namespace, **limits: int) -> None:
    """Upper bounds where a typo would run for ever or exhaust memory."""
    for name, limit in limits.items():
        v = getattr(args, name)
        if v is not None and v > limit:
            raise ValueError(f"--{name.replace('_', '-')} must be at most {limit}, got {v}")


def cmd_train(args: argparse.Namespace) -> int:
    import importlib.util
    import tempfile
    from dataclasses import replace

    from .diagnose.data_quality import pauses
    from .report.training import training_output_paths, write_training_outputs
    from .train import default_selection, member_state_paths, train

    _positive(args, "epochs", "history", "eval_every", "select_runs", "members", "jobs")
    _at_most(args, epochs=1_000_000, history=10_000, eval_every=1_000_000, members=MAX_MEMBERS, jobs=1024)
    hidden = None if args.hidden is None else parse_hidden(args.hidden)
    if not 0 <= args.play_width <= 1:
        raise ValueError(f"--play-width is a fraction of the action range (0..1), got {args.play_width}")
    if not 0 <= args.multistep <= 1000:
        raise ValueError(f"--multistep is a number of steps (0..1000), got {args.multistep}")
    if args.input_noise is not None and not 0 <= args.input_noise <= 100:  # NaN fails the comparison too
        raise ValueError(f"--input-noise is a multiple of the typical step (0..100), got {args.input_noise}")
    if args.lr is not None and not 0 < args.lr < 1e3:  # NaN fails too; inf once trained to a NaN model
        raise ValueError(f"--lr must be a positive learning rate below 1000, got {args.lr}")
    if args.patience is not None and args.patience < 0:
        raise ValueError(f"--patience must be at least 0, got {args.patience}")
    if Path(args.output).is_dir():  # found before the training, not when saving it
        raise ValueError(f"--output {args.output}: is a folder; name the model file, e.g. model.pt")
    if Path(args.output).suffix.lower() == ".onnx":  # the name every command reads as an exported model
        raise ValueError(
            f"--output {args.output}: .onnx names an exported model; save the checkpoint as .pt "
            "and export it with envi-export"
        )
    writable_file(args.output, "--output")
    logs = read_logs(args, min_length=args.history + 1)
    val = read_logs(args, "val_logs", min_length=args.history + 1) if args.val_logs else []
    if val and val[0].meta.schema.columns != logs[0].meta.schema.columns:  # once a numpy broadcast error
        raise ValueError(
            f"{val[0].path or val[0].name}: columns {','.join(val[0].meta.schema.columns)} differ from the "
            f"training logs' ({logs[0].path or logs[0].name}: {','.join(logs[0].meta.schema.columns)})"
        )
    output = Path(args.output)
    given = [*args.logs, *(args.val_logs or []), args.system, args.config]
    refuse_overwriting(
        [output, *training_output_paths(output)], [*(lg.path for lg in (*logs, *val)), *given], "--output"
    )
    refuse_writing_among_logs(training_output_paths(output), [lg.path for lg in (*logs, *val)], f"--output {output}")
    for finding in pauses([*logs, *val]):  # what envi diagnose flags first, said before the training
        note(f"envi train: note: {finding.what}")
    gappy = {str(lg.path or lg.name): lg.meta.breaks for lg in (*logs, *val) if lg.meta.breaks}
    for name, breaks in gappy.items():  # the collector marked missing rows: no window spans them
        rows = ", ".join(map(str, breaks[:5])) + (f", ... ({len(breaks)} in all)" if len(breaks) > 5 else "")
        text = f"{name}: rows are missing before row(s) {rows}; no training window spans them"
        note(f"envi train: note: {text}")
    system = system_of(args) or describe_schema(logs[0].meta.schema)  # what train() would take
    runs = {"runs": args.select_runs} if args.select_runs else {}  # else the description's, else the trainer's
    kwargs: dict[str, Any] = {"seed": args.seed, "history": args.history, "progress": not args.quiet}
    if args.algorithm != "random":
        kwargs.update(
            epochs=args.epochs,
            eval_every=args.eval_every,
            extras=tuple(args.extras),
            play_width=args.play_width,
            selection=replace(default_selection(system), patience=args.patience, **runs),
        )
        if args.algorithm == "bc":
            kwargs.update(head=args.head, multistep=args.multistep)
            if args.input_noise is not None:  # else the system description's [training] default
                kwargs["input_noise"] = args.input_noise
        elif args.multistep or args.input_noise:
            raise ValueError(f"--multistep and --input-noise are behaviour-cloning losses, not {args.algorithm}'s")
        elif args.head == "deterministic":
            raise ValueError(f"--head deterministic: {args.algorithm} trains a Gaussian policy (PPO needs one)")
        if args.residual is not None:  # else the system description's [training] default
            kwargs["residual"] = args.residual
        if args.context is not None:  # else the system description's [training] default
            kwargs["context"] = args.context
        if args.step_noise is not None:  # else the system description's [training] default
            if args.head == "deterministic" and args.step_noise != "gaussian":
                raise ValueError(
                    f"--step-noise {args.step_noise} shapes a Gaussian head's draws; --head deterministic has none"
                )
            kwargs["step_noise"] = args.step_noise
        if args.lr is not None:
            kwargs["lr"] = args.lr
        if args.lr_schedule is not None:  # else the system description's [training] default
            if args.algorithm != "bc":
                raise ValueError(f"--lr-schedule is behaviour cloning's step size, not {args.algorithm}'s")
            kwargs["lr_schedule"] = args.lr_schedule
        if args.members is not None:  # else the system description's [training] default
            kwargs["members"] = args.members
        if hidden is not None:  # else the description's, else the trainer's
            kwargs["hidden"] = hidden
    elif args.members not in (None, 1):
        raise ValueError("--members: the random baseline has no training to repeat")
    if args.algorithm != "random":
        kwargs.update(state_path=state_path(Path(args.output)), resume=args.resume)
    elif args.resume:
        raise ValueError("--resume: random training has no epochs, so there is nothing to resume")
    if args.tensorboard and importlib.util.find_spec("tensorboard") is None:
        raise ValueError("--tensorboard needs the tensorboard package: pip install 'envi[tensorboard]'")
    losses = tempfile.TemporaryDirectory() if args.algorithm in ("gail", "bcxgail") else None
    if losses is not None:
        kwargs["curves_dir"] = losses.name  # GAIL's per-epoch losses, merged into the curves below
    t0 = time.perf_counter()
    jobs = args.jobs or os.cpu_count() or 1
    release()  # every check has passed: the notes before the training, not after it
    ckpt = train(args.algorithm, logs, val, system=system, jobs=jobs, **kwargs)
    path = ckpt.save(args.output)
    written = write_training_outputs(
        ckpt,
        Path(path),
        Path(losses.name) / "curves.csv" if losses is not None else None,
        Path(args.tensorboard) if args.tensorboard else None,
    )
    if losses is not None:
        losses.cleanup()
    if args.algorithm != "random":  # finished: nothing to resume
        for done in member_state_paths(state_path(Path(args.output)), ckpt.size):
            done.unlink(missing_ok=True)
    sel = ckpt.record.selection
    if sel.get("warning"):
        note(f"envi train: warning: {sel['warning']}")
    epochs = [m.get("best_epoch", "-") for m in sel.get("members", [sel])]
    what = f", {ckpt.size} members (seeds {args.seed}..{args.seed + ckpt.size - 1})" if ckpt.members else ""
    print(
        f"trained {args.algorithm}{what} on {len(logs)} logs "
        f"({len(val)} validation) in {time.perf_counter() - t0:.1f} s; selected epoch "
        f"{', '.join(map(str, epochs))}; saved {path}"
    )
    print("training curves: " + " ".join(str(p) for p in written.values()))
    return 0


# ------------------------------------------------------------------------------------ simulate


def load_model(args: argparse.Namespace) -> Checkpoint:
    """``--model``, with the effect layers of ``--layers`` around it when given: the model every
    simulating command (simulate, check) runs."""
    from .effect_layers import read_layers
    from .model import Checkpoint

    ckpt = Checkpoint.load(args.model)
    return ckpt.with_layers(read_layers(args.layers)) if args.layers else ckpt


#: The most simulated rows one ``envi simulate`` writes as logs (about 2 GB of CSV at 20 bytes a row)
MAX_SIMULATED_ROWS = 100_000_000


def cmd_simulate(args: argparse.Namespace) -> int:
    from .effect_layers import describe
    from .logs import group_by_controller
    from .simulate import choose_engine, draws_at_random, iter_simulate, versions_to_simulate

    _positive(args, "runs")
    _at_most(args, runs=100_000_000)
    if args.steps is not None and not 1 <= args.steps <= 1_000_000:  # 0 once wrote logs of the window alone
        raise ValueError(f"--steps must lie in 1..1000000, got {args.steps}")
    out = output_folder(args.out)
    refuse_earlier_logs(out, args.force)  # before any work: new runs among old ones read back as one set
    params = parse_params(args.param, "--param")  # a NaN gain once simulated NaN logs
    if args.param and not args.controller:
        raise ValueError(
            "--param sets the parameters of --controller; without it each initial log's own controller runs"
        )
    ckpt = load_model(args)
    init = logs_fit_model(
        read_logs(args, "init_logs", min_length=ckpt.config.history), ckpt.schema, args.model, ckpt.record.period_ms
    )
    note_starts_across_breaks("envi simulate", init, ckpt.config.history)
    inside = [lg.path for lg in init if lg.path is not None and lg.path.resolve().parent == out.resolve()]
    if inside:  # --force would delete the very logs the simulation starts from
        raise ValueError(f"--out {out}: holds the initial log {inside[0].name}; simulate into another folder")
    rows = sum(args.runs * (args.steps if args.steps is not None else len(lg) - ckpt.config.history) for lg in init)
    if rows > MAX_SIMULATED_ROWS:  # once 10^8 runs started silently toward filling the disk
        raise ValueError(
            f"--runs {args.runs}: {len(init)} initial log(s) x {args.runs} runs would write {rows:,} simulated rows "
            f"as logs, more than {MAX_SIMULATED_ROWS:,}; for mass verification score runs without writing them "
            "(envi check, or envi_sim --metrics)"
        )
    given = ControllerSpec(args.controller, params) if args.controller else None
    specs = [given] if given else list(group_by_controller(init))
    stems = [Path(lg.path).stem if lg.path else lg.meta.run_id for lg in init]
    dup = sorted({st for st in stems if stems.count(st) > 1})
    if dup:
        raise ValueError(
            f"initial logs from different folders share the name {dup[0]!r}: their simulated runs would "
            "overwrite each other; simulate them into separate --out folders"
        )
    source = {spec: group[0].path for spec, group in group_by_controller(init).items()}
    for spec in specs:  # an unknown controller is one error line naming its log, before any engine note
        try:
            spec.build(len(ckpt.schema.states), len(ckpt.schema.actions), ckpt.period_ms)
        except ValueError as exc:
            raise ValueError(f"{source[spec]}: {exc}" if spec is not given else str(exc)) from None
    engines = {choose_engine(ckpt, spec, args.engine, args.mean) for spec in specs}
    if args.engine == "auto" and "torch" in engines:
        from .native import unsupported

        for spec in specs:
            why = unsupported(ckpt, spec, args.mean)
            if why:
                note(f"envi simulate: the native engine cannot run {spec.label()} ({why}); using PyTorch")
    if args.runs > 1 and not draws_at_random(ckpt, args.mean):
        note(
            f"envi simulate: the model draws nothing at random ({'--mean' if args.mean else 'a deterministic head'}"
            f"): the {args.runs} runs of each initial log are one run written {args.runs} times"
        )
    t0 = time.perf_counter()
    n = 0
    release()  # every check has passed: the notes before the simulations, not after them
    with staged_logs(out, args.force) as staging:  # a failure mid-way leaves --out as it was
        for spec, group in versions_to_simulate(init, given):
            for _, _, lg in iter_simulate(ckpt, spec, group, args.steps, args.runs, args.seed, args.engine, args.mean):
                write_log(lg, staging.folder / f"{lg.meta.run_id}.csv")  # run ids are plain names: no path escapes
                n += 1
    replaced = staging.replaced
    said = f" (replaced {replaced} earlier logs)" if replaced else ""
    said += f"; effect layers: {describe(ckpt.layers)}" if ckpt.layers else ""
    print(f"simulated {n} runs in {time.perf_counter() - t0:.2f} s ({'+'.join(sorted(engines))} engine) -> {out}{said}")
    return 0


# ------------------------------------------------------------------------------------ verify


def note_starts_across_breaks(command: str, logs: Sequence[Log], history: int) -> None:
    """Name each log whose initial window (sigma_0, its first ``history`` rows) holds rows on both
    sides of missing rows: simulations start from a state the system was never in."""
    for lg in logs:
        if lg.meta.breaks and lg.meta.breaks[0] < history:
            note(
                f"{command}: note: {lg.path or lg.name}: rows are missing before row {lg.meta.breaks[0]}, inside "
                f"the initial window of {history} rows its simulations start from"
            )


def note_sources(command: str, option: str, logs: Sequence[Log], want_sim: bool) -> None:
    """Say when an option's logs are not what it takes (simulations for ``--sim``: the model's, or
    hardware in its loop; field or twin runs for ``--real``) by their sidecars' ``source``. They are
    scored as given, since a twin may stand in for reality on purpose, but never without a word."""
    odd = [lg for lg in logs if (lg.meta.source in SIMULATED_SOURCES) != want_sim]
    if odd:
        sources = ", ".join(sorted({repr(lg.meta.source) for lg in odd}))
        note(
            f"{command}: note: {len(odd)} of the {len(logs)} {option} log(s) (e.g. {odd[0].path or odd[0].name}) "
            f"say source {sources} in their sidecars, not {'a simulation' if want_sim else 'a real run'}; "
            "scored as given"
        )


def cmd_verify(args: argparse.Namespace) -> int:
    from .logs import group_by_controller
    from .verify import to_text, verify, write_report

    if args.out:
        output_folder(args.out)
    real = read_logs(args, "real")
    sim = load_logs(args.sim, skip_bad=args.skip_bad)
    unknown = [lg for lg in sim if lg.meta.controller is None]
    if unknown and len(unknown) == len(sim):  # real logs given as --sim, most likely
        raise ValueError(
            f"{unknown[0].path or unknown[0].name}: none of the {len(sim)} --sim log(s) says its controller "
            "version (no sidecar): --sim takes what envi simulate wrote, real logs go to --real"
        )
    if unknown:  # a simulated log whose sidecar went missing: its version cannot be told
        note(
            f"envi verify: note: {len(unknown)} simulated run(s) (e.g. {unknown[0].path or unknown[0].name}) do not "
            "say their controller version (no sidecar); not scored"
        )
        sim = [lg for lg in sim if lg.meta.controller is not None]
    system = system_of(args)
    results = verify(real, sim, system, skip=args.skip, floor=not args.no_floor, seed=args.seed)
    note_sources("envi verify", "--real", real, want_sim=False)  # after the checks: an error stays one line
    note_sources("envi verify", "--sim", sim, want_sim=True)
    real_versions = set(group_by_controller(real))
    for spec, group in group_by_controller(sim).items():
        if spec not in real_versions:  # say so: a simulated log whose sidecar went missing lands here
            note(
                f"envi verify: note: {len(group)} simulated run(s) of {spec.label()} "
                f"(e.g. {group[0].path or group[0].name}) have no real runs of that version; not scored"
            )
    print(to_text(results))
    if args.out:
        md, js = write_report(results, Path(args.out), real=real, sim=sim, system=system, skip=args.skip)
        print(f"report: {md.with_suffix('.html')} {md} {js}")
    return 0


# ------------------------------------------------------------------------------------ check

#: simulated runs per look of envi check's sequential test. Why 10: a look costs milliseconds, while a look
#: of 100 made every verdict cost at least 100 runs, 0.57x the fixed-size test at the car twin's
#: P >= 0.8; with 10 the twin's versions decide after a median of 10-40 runs (0.06-0.23x).
DEFAULT_CHECK_BATCH = 10


def cmd_check(args: argparse.Namespace) -> int:
    """A verdict per controller version and requirement, for the real system, with as few runs as needed."""
    import datetime

    from . import __version__
    from .check import check, requirements_of, write_check
    from .effect_layers import layers_json
    from .report.requirements import real_only_text

    if not 0 < args.alpha < 0.5:
        raise ValueError(f"--alpha must lie in (0, 0.5), got {args.alpha}")
    if not 0 < args.delta < 0.5:  # 5 was once accepted: an indifference region wider than [0, 1]
        raise ValueError(f"--delta must lie in (0, 0.5), got {args.delta}")
    _positive(args, "max_runs", "batch", "sims_per_start")
    _at_most(args, max_runs=10_000_000, batch=1_000_000, sims_per_start=100_000)
    if args.batch is None:  # a cap below the default batch is one look of the whole cap
        args.batch = min(DEFAULT_CHECK_BATCH, args.max_runs)
    elif args.batch > args.max_runs:  # once ran --max-runs silently, as if the batch had been the cap
        raise ValueError(f"--batch {args.batch} is more than --max-runs {args.max_runs}: give at most the cap")
    if args.out:
        output_folder(args.out)
    ckpt = load_model(args)
    real = logs_fit_model(
        read_logs(args, "real", min_length=ckpt.config.history + 1), ckpt.schema, args.model, ckpt.record.period_ms
    )
    note_starts_across_breaks("envi check", real, ckpt.config.history)  # each real run starts paired simulations
    system = ckpt.system
    # the requirements of the description the user names, not silently the checkpoint's older copy
    reqs = requirements_of(load_system(args.system) if args.system else system, args.require or [], args.probability)
    for v in args.unseen or []:  # a misspelt or NaN parameter, before the simulations
        finite_numbers(parse_where_one(v), f"--unseen {v!r} values")
        if system:
            system.check_version_fields(parse_where_one(v), f"--unseen {v!r}")
    unseen = [
        system.controller_for(parse_where_one(v)) if system and system.controller else None for v in args.unseen or []
    ]
    if any(u is None for u in unseen):
        raise ValueError("--unseen needs a system description with a [controller] to build the version from")
    extra = ckpt.recorded_logs("data", missing_ok=True) + ckpt.recorded_logs("validation", missing_ok=True)
    rows = check(
        ckpt,
        real,
        reqs,
        [u for u in unseen if u is not None],
        extra,
        alpha=args.alpha,
        delta=args.delta,
        max_runs=args.max_runs,
        batch=args.batch,
        sims_per_start=args.sims_per_start,
        seed=args.seed,
        engine=args.engine,
    )
    meta = {
        "model": str(args.model),
        "envi": __version__,
        "command": " ".join(sys.argv),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "alpha": args.alpha,
        "delta": args.delta,
        "max_runs": args.max_runs,
        "batch": args.batch,
        "sims_per_start": args.sims_per_start,
        "seed": args.seed,
        "system": system.name if system else None,
        **({"layers": layers_json(ckpt.layers)} if ckpt.layers else {}),
    }
    width = max(len(r.version) for r in rows)
    named = max(len("requirement"), *(len(r.requirement) for r in rows))
    print(
        f"{'version':<{width}} {'requirement':<{named}} {'P req':>6} {'real':>4} {'sim runs':>8} "
        f"{'P real system':>16} {'basis':<11} {'verdict':<9} real runs only"
    )
    for r in rows:
        q = r.real_system
        print(
            f"{r.version:<{width}} {r.requirement:<{named}} {r.p_required:>6g} {r.n_real:>4} "
            f"{r.simulation['runs']:>8} [{q['interval'][0]:.3f}, {q['interval'][1]:.3f}] {q['basis'][:11]:<11} "
            f"{r.verdict:<9} {real_only_text(q)}"
        )
    if args.out:
        md, js = write_check(rows, Path(args.out), meta)
        print(f"report: {md.with_suffix('.html')} {md} {js}")
    return 0


def parse_where_one(text: str) -> dict[str, Any]:
    """``kp_steer=0.8,kp_speed=18`` -> ``{"kp_steer": 0.8, "kp_speed": 18.0}``."""
    out: dict[str, Any] = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--unseen {text!r}: expected name=value[,name=value]")
        if key.strip() in out:  # 'x=1,x=2' ran as x=2
            raise ValueError(f"--unseen {text!r}: {key.strip()!r} is given twice")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            out[key.strip()] = value.strip()
    return out


# ------------------------------------------------------------------------------------ demo


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job on the project's own data: twin logs -> split -> BC -> simulate -> verify."""
    from .demo import FAST, FULL, run_demo

    _positive(args, "epochs")
    run_demo(Path(args.out), seed=args.seed, system=args.system, size=FAST if args.fast else FULL, epochs=args.epochs)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = EnviParser(
        prog="envi", description="Learn an environment model from field logs and verify a controller against it."
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks")
    parser.add_argument(
        "--config",
        metavar="RUN.toml",
        help="take a command's options from the [command] table of a TOML run file (the command line wins); "
        "the effective configuration is written beside the output as run.toml",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=EnviParser)

    p = sub.add_parser("init", help="draft a system description (TOML) from a folder of logs")
    p.add_argument("--logs", required=True, help="a folder of CSV logs")
    p.add_argument("--pattern", default=None, help="file name pattern, e.g. 'log_{x}_{run}.csv' (default: guessed)")
    p.add_argument("-o", "--output", default="system.toml", help="file to write (default system.toml)")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")
    p.set_defaults(func=cmd_init)

    p = sub.add_parser("split", help="choose train/validation/test logs; writes train.json, val.json, test.json")
    add_log_args(p)
    p.add_argument("--train", type=int, default=None, help="training logs per version (default: all the rest)")
    p.add_argument("--val", type=int, default=0, help="validation logs per version (model selection)")
    p.add_argument("--test", type=int, default=0, help="test logs per version (verification)")
    p.add_argument("--total", action="store_true", help="the counts are totals over all versions, not per version")
    p.add_argument(
        "--mode",
        choices=("random", "blocks"),
        default="random",
        help="random: seeded draw; blocks: test logs are the last ones in file order (the real "
        "logs are consecutive slices of one run, so blocks keeps neighbours apart)",
    )
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument(
        "--out",
        required=True,
        help="folder for train.json, val.json and test.json (all three rewritten by every split: none is left "
        "from an earlier one)",
    )
    p.set_defaults(func=cmd_split)

    p = sub.add_parser("train", help="train an environment model")
    add_log_args(p, help="training logs")
    p.add_argument("--val-logs", nargs="*", default=None, help="validation logs for closed-loop model selection")
    p.add_argument(
        "--algorithm",
        choices=("bc", "gail", "bcxgail", "random"),
        default="bc",
        help="bc: behaviour cloning; gail, bcxgail: adversarial (PPO); random: the paper's baseline",
    )
    p.add_argument("--epochs", type=int, default=300, help="training epochs")
    p.add_argument(
        "--lr-schedule",
        choices=LR_SCHEDULES,
        default=None,
        help="BC's step size over the epochs: constant, or cosine (annealed to 0 over --epochs, then trained to "
        "that cap whatever --patience says) (default: the system description's [training] lr_schedule, else "
        "constant)",
    )
    p.add_argument(
        "--lr", type=float, default=None, help="learning rate (default: the algorithm's: BC 1e-3, GAIL/BCxGAIL 5e-5)"
    )
    p.add_argument("--history", type=int, default=10, help="window length l")
    p.add_argument(
        "--hidden",
        default=None,
        help="hidden widths, comma-separated (default: the system description's [training] hidden, else 256,256)",
    )
    p.add_argument(
        "--head",
        choices=("deterministic", "gaussian"),
        default="gaussian",
        help="gaussian: mean and spread of the next state, simulated by sampling (reproduces the "
        "real runs' spread); deterministic: the mean only (bc only)",
    )
    p.add_argument(
        "--extras",
        nargs="*",
        choices=EXTRA_CHANNELS,
        default=[],
        help="derived input channels (what a diagnosis' fix may add): dt, phase, play",
    )
    p.add_argument(
        "--play-width", type=float, default=0.0, help="the play channel's full width, a fraction of the action range"
    )
    p.add_argument(
        "--context",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the model also reads sigma_0's per-state mean and spread at every step (default: the system "
        "description's [training] context)",
    )
    p.add_argument(
        "--residual",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the model predicts the change from the window's last state (default: the system "
        "description's [training] residual: on for the car, off for lane keeping, as measured)",
    )
    p.add_argument(
        "--step-noise",
        choices=STEP_NOISES,
        default=None,
        help="a Gaussian head's draws: normal, a Student-t of the same variance, or a two-scale normal of "
        "the same variance (a share of steps drawn wider), the shape fitted after training in closed loop "
        "on the validation logs (default: the system description's [training] step_noise: student-t for "
        "lane keeping, as measured; else gaussian)",
    )
    p.add_argument(
        "--multistep",
        type=int,
        default=0,
        help="bc: add the loss of the model unrolled this many steps on its own predictions (0: none)",
    )
    p.add_argument(
        "--input-noise",
        type=float,
        default=None,
        help="bc: perturb the training windows' states by this many times their typical logged step "
        "(default: the system description's [training] input_noise, else 0: none)",
    )
    p.add_argument("--eval-every", type=int, default=10, help="epochs between closed-loop validations")
    p.add_argument(
        "--select-runs",
        type=int,
        default=None,
        help="simulated runs per validation log at each validation "
        "(default: the system description's [training] select_runs, else 5)",
    )
    p.add_argument(
        "--patience",
        type=int,
        default=10,
        help="validations without a better (smoothed) score before training stops before --epochs; 0: never",
    )
    p.add_argument(
        "--members",
        type=int,
        default=None,
        help="train a seed ensemble of this many models (seeds --seed onwards), each simulated run drawn by "
        "one of them: runs then carry what the logs leave undecided between trainings (default: the "
        "system description's [training] members, else 1)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="members trained at once, each in a process of one torch thread (default: the machine's cores)",
    )
    p.add_argument("--seed", type=seed_type, default=0, help="seed of initialisation and sampling")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue a killed training from <output>.state (written at every validation; bc, gail, bcxgail)",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        help="checkpoint file to write (an existing one is replaced); its training curves go beside it "
        "(MODEL.curves.csv, MODEL.training.html)",
    )
    p.add_argument(
        "--tensorboard",
        metavar="DIR",
        default=None,
        help="also write the training curves as TensorBoard scalars into DIR (needs pip install 'envi[tensorboard]')",
    )
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("simulate", help="simulate a controller against a model from real initial windows")
    p.add_argument("--model", required=True)
    add_log_args(p, "--init-logs", help="logs whose first l rows start the simulations")
    p.add_argument(
        "--controller",
        default=None,
        help="controller name or package.module:function (default: each log's own controller)",
    )
    p.add_argument("--param", nargs="*", default=None, help="parameters of --controller, e.g. x=30")
    p.add_argument("--runs", type=int, default=1, help="runs per initial window")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="steps after the window (default: each initial log's length minus the window)",
    )
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument(
        "--engine",
        choices=("auto", "native", "torch"),
        default="auto",
        help="auto (default): the C++ engine when it can run the model, else PyTorch",
    )
    p.add_argument(
        "--mean",
        action="store_true",
        help="simulate a stochastic model by its mean (no sampling): one deterministic run per window",
    )
    p.add_argument(
        "--layers",
        default=None,
        help="effect layers file (as envi diagnose writes it): simulate the model with these effects added "
        "(a delay, a lag, play, noise, ...), on either engine",
    )
    p.add_argument(
        "--out",
        required=True,
        help="folder for simulated logs (CSV with .meta.json sidecars); refused when it already holds logs",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the logs --out already holds: its CSV files and .meta.json sidecars are deleted "
        "before writing (any other file stays), so the folder holds exactly this run",
    )
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("verify", help="compare real and simulated logs: accuracy, distances, floor")
    add_log_args(p, "--real", help="real logs")
    p.add_argument("--sim", nargs="+", required=True, help="simulated logs (with sidecars)")
    p.add_argument("--skip", type=int, default=10, help="leading rows not scored (the initial window)")
    p.add_argument("--no-floor", action="store_true", help="skip the real-vs-real reference and its tests")
    p.add_argument("--seed", type=seed_type, default=0)
    p.add_argument(
        "--out", default=None, help="folder for report.md, .html, .json; an earlier report there is replaced as a whole"
    )
    p.set_defaults(func=cmd_verify)

    p = sub.add_parser(
        "check",
        help="verdict per version and requirement: P(goal) with an interval, for the real "
        "system, deciding with as few simulated runs as needed",
    )
    p.add_argument("--model", required=True, help="checkpoint (.pt)")
    add_log_args(
        p,
        "--real",
        help="real logs: their initial windows start the simulations, their outcomes "
        "make the verdict about the real system",
    )
    p.add_argument(
        "--require",
        nargs="*",
        default=None,
        metavar="EXPR[@P]",
        help="requirements, e.g. 'max_abs_dev(color, 40) <= 35@0.9' or 'always (distance >= 10)' "
        "(default: the system description's)",
    )
    p.add_argument(
        "--probability", type=float, default=None, help="required probability of --require without '@P' (default 0.9)"
    )
    p.add_argument(
        "--unseen",
        nargs="*",
        default=None,
        metavar="NAME=VALUE[,...]",
        help="versions never field-tested (TMVU), e.g. x=20; their verdict rests on the model",
    )
    p.add_argument("--alpha", type=float, default=0.05, help="each wrong PASS or FAIL has probability at most alpha")
    p.add_argument(
        "--delta",
        type=float,
        default=0.05,
        help="indifference region of the sequential test around the required probability",
    )
    p.add_argument("--max-runs", type=int, default=4000, help="simulated runs at most per version and requirement")
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        help=f"simulated runs per look of the sequential test (default {DEFAULT_CHECK_BATCH}; --max-runs when less)",
    )
    p.add_argument(
        "--sims-per-start",
        type=int,
        default=40,
        help="simulated runs from each real run's own initial window (its paired prediction; 40 keeps a "
        "faithful model's interval within 0.6x the real-only one on the car twin, 20 does not)",
    )
    p.add_argument("--seed", type=seed_type, default=0, help="seed of the simulations")
    p.add_argument("--engine", choices=("auto", "native", "torch"), default="auto", help="simulation engine")
    p.add_argument(
        "--layers",
        default=None,
        help="effect layers file (as envi diagnose writes it): the verdicts of the model with these effects "
        "added, a what-if (recorded in the report's provenance)",
    )
    p.add_argument(
        "--out", default=None, help="folder for check.md, .html, .json; an earlier report there is replaced as a whole"
    )
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("demo", help="the main job on the built-in twin data")
    p.add_argument(
        "--system", choices=("lane-keeping", "car"), default="lane-keeping", help="which twin system plays the field"
    )
    p.add_argument("--fast", action="store_true", help="a small demo (fewer logs, 40 epochs): half the time")
    p.add_argument(
        "--out",
        default="demo_out",
        help="output folder (default demo_out); a second demo replaces the logs the first left in its data/ "
        "and sim/ subfolders (their CSV and .meta.json files only), the model and the report",
    )
    p.add_argument("--seed", type=seed_type, default=0, help="seed of the twin, training and simulation")
    p.add_argument("--epochs", type=int, default=None, help="training epochs (default: 300, --fast 40)")
    p.set_defaults(func=cmd_demo)

    # subcommands contributed by other parts of the project, each registering its own parsers
    for register in (register_twin, register_experiment, register_diagnose, register_brick_sim):
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    from .run_config import apply_config, command_parser, take_config, write_effective

    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        argv, config = take_config(argv)
        if config is not None:
            apply_config(parser, argv, config)
    except ValueError as exc:
        print(f"envi: error: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    empty = next((k for k, v in vars(args).items() if v == "" or isinstance(v, list) and "" in v), None)
    if empty is not None:  # '--out ""' once wrote into the current folder, and a report nowhere
        nested = [v for k, v in vars(args).items() if k.endswith("_command") and isinstance(v, str)]
        name = " ".join([args.command, *nested])  # as the sub-command says its own errors: 'envi twin generate'
        print(f"envi {name}: error: --{empty.replace('_', '-')}: an empty value", file=sys.stderr)
        return 2
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        with signals_interrupt(), held_notes(f"envi {args.command}"):  # kill cleans up as Ctrl-C; notes after checks
            rc = func(args)
        if config is not None and rc == 0:
            written = write_effective(args, command_parser(parser, argv)[0])
            if written is not None:
                print(f"effective configuration: {written}")
        return rc
    except MemoryError:  # one line, as any other refusal; the sizes checked up front make it rare
        print(f"envi {args.command}: error: out of memory; ask for fewer runs or a smaller model", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        if "can't allocate memory" not in str(exc):  # torch's allocator, the same condition
            raise
        print(f"envi {args.command}: error: out of memory ({str(exc).splitlines()[0][:120]})", file=sys.stderr)
        return 2
    except BrokenPipeError:  # 'envi twin effects | head': the reader stopped; quietly, as a shell's SIGPIPE
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit's flush
        return 141  # not 0: the command may not have finished (a report after the printed table)
    except (LogError, ValueError, OSError, KeyError) as exc:
        if args.debug:
            raise
        msg = one_line(str(exc)) or type(exc).__name__
        if isinstance(exc, OSError) and exc.filename and exc.strerror:  # not '[Errno 17] File exists: ...'
            why = "exists and is not a folder" if isinstance(exc, FileExistsError) else exc.strerror
            msg = one_line(f"{exc.filename}: {why}")
        print(f"envi {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"envi {args.command}: interrupted{f' ({exc})' if isinstance(exc, Terminated) else ''}", file=sys.stderr)
        return exit_code(exc)


if __name__ == "__main__":
    sys.exit(main())

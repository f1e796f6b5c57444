"""Run files: a command's options from a TOML file (``envi train --config run.toml``), written back.

A run file holds one table per command (``[train]``, ``[simulate]``, ``[twin.generate]`` for nested
ones), with option names as on the command line (``val-logs`` or ``val_logs``)::

    [train]
    logs = ["work/split/train.json"]
    val-logs = ["work/split/val.json"]
    epochs = 100
    output = "work/bc.pt"

Options given on the command line win over the file. Every value is checked as the command line
checks it (its type, its choices), and an unknown option is an error naming the file, the table and
the option, so a typo never runs with a default silently. After a successful run the effective
configuration (every option of the command, from the file, the command line or the defaults) is
written beside the output as ``run.toml``, so the run can be repeated from that one file.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .atomic import atomic_write_text
from .files import parse_toml, read_text

#: Namespace entries that are not options of a command.
NOT_OPTIONS = {"func", "parser", "debug", "config", "help"}


def take_config(argv: list[str]) -> tuple[list[str], Path | None]:
    """``argv`` without ``--config FILE`` / ``--config=FILE``, and that file."""
    out, path, i = [], None, 0
    while i < len(argv):
        a = argv[i]
        if a == "--config":
            if i + 1 >= len(argv):
                raise ValueError("--config needs a file (a TOML run file)")
            path, i = Path(argv[i + 1]), i + 2
            continue
        if a.startswith("--config="):
            path = Path(a.split("=", 1)[1])
        else:
            out.append(a)
        i += 1
    return out, path


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def command_parser(parser: argparse.ArgumentParser, argv: Sequence[str]) -> tuple[list[str], argparse.ArgumentParser]:
    """The command names in ``argv`` (``["twin", "generate"]``) and the parser of the last one."""
    names: list[str] = []
    current = parser
    for token in argv:
        choices = _subparsers(current)
        if not choices:
            break
        if token in choices:
            names.append(token)
            current = choices[token]
    if not names:
        raise ValueError("--config needs a command (e.g. envi train --config run.toml)")
    return names, current


def _convert(action: argparse.Action, value: Any, where: str) -> Any:
    """A TOML value as the command line would have parsed it."""
    # --x/--no-x (BooleanOptionalAction) too: the run.toml envi writes holds them as true/false
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse.BooleanOptionalAction)):
        if not isinstance(value, bool):
            raise ValueError(f"{where}: must be true or false, not {value!r:.40}")
        return value
    many = action.nargs in ("*", "+") or isinstance(action.nargs, int)
    items = value if isinstance(value, list) else [value]
    if not many and isinstance(value, list):
        raise ValueError(f"{where}: takes one value, not a list")
    out = []
    for item in items:
        # a bool is an int to Python: ``epochs = true`` once trained "True" epochs and recorded it
        bad = isinstance(item, (dict, list, bool)) or (isinstance(item, float) and not math.isfinite(item))
        if bad:
            raise ValueError(f"{where}: {item!r:.40} is not a value this option takes")
        v = item
        if action.type is None and not isinstance(item, str):  # a path or name: 'out = 5' once reached os.fspath
            raise ValueError(f"{where}: takes text, not {item!r:.40}: write it in quotes")
        if action.type is int and isinstance(item, float):  # int('2.0') said 'invalid literal for int()'
            raise ValueError(f"{where}: must be a whole number, not {item!r:.40}")
        if action.type is not None:
            try:
                v = action.type(str(item))
            except (TypeError, ValueError, argparse.ArgumentTypeError) as exc:
                raise ValueError(f"{where}: {exc}") from None
        if action.choices is not None and v not in action.choices:
            raise ValueError(f"{where}: {v!r} is not one of {', '.join(map(str, action.choices))}")
        out.append(v)
    return out if many else out[0]


def apply_config(parser: argparse.ArgumentParser, argv: Sequence[str], path: Path) -> None:
    """Make ``path``'s table for the command in ``argv`` that command's defaults (checked)."""
    if not path.exists():
        raise ValueError(f"{path}: no such run file")
    data = parse_toml(read_text(path, "a run file"), str(path), "a run file")
    names, sub = command_parser(parser, argv)
    table: Any = data
    for depth, name in enumerate(names):
        if depth and isinstance(table, dict):  # '[twin] out' beside '[twin.generate]' was ignored
            stray = sorted(k for k, v in table.items() if not isinstance(v, dict))
            if stray:
                where = ".".join(names[:depth])
                raise ValueError(
                    f"{path}: [{where}] {stray[0]}: envi {' '.join(names[:depth])} takes its options in its "
                    f"sub-command's table ([{where}.{name}])"
                )
        table = table.get(name, {}) if isinstance(table, dict) else {}
    key = ".".join(names)
    if not isinstance(table, dict) or not table:
        raise ValueError(f"{path}: no [{key}] table for envi {' '.join(names)}")
    nested = _subparsers(sub)
    actions = {a.dest: a for a in sub._actions if a.dest not in NOT_OPTIONS and a.option_strings}
    defaults = {}
    for raw, value in table.items():
        if raw in nested and isinstance(value, dict):
            continue
        dest = raw.replace("-", "_")
        if dest not in actions:
            known = ", ".join(sorted(d.replace("_", "-") for d in actions))
            raise ValueError(f"{path}: [{key}] has no option {raw!r} (envi {' '.join(names)} takes: {known})")
        action = actions[dest]
        defaults[dest] = _convert(action, value, f"{path}: [{key}] {raw}")
        action.required = False  # given by the file; the command line may still override it
    sub.set_defaults(**defaults)


def _toml_value(v: Any) -> str | None:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)) and math.isfinite(v):
        return repr(v)
    if isinstance(v, (str, Path)):
        s = str(v).replace("\\", "\\\\").replace('"', '\\"')
        return f'"{s}"'
    if isinstance(v, (list, tuple)):
        parts = [_toml_value(x) for x in v]
        return None if any(p is None for p in parts) else "[" + ", ".join(p for p in parts if p is not None) + "]"
    return None  # None and anything TOML cannot hold: left out (the default applies again)


def effective_toml(args: argparse.Namespace, names: Sequence[str]) -> str:
    """Every option of the command as a run file that repeats it."""
    lines = [f"# the effective configuration of: envi {' '.join(names)}", f"[{'.'.join(names)}]"]
    for dest, value in sorted(vars(args).items()):
        if dest in NOT_OPTIONS or dest in ("command",) or dest.endswith("_command"):
            continue
        text = _toml_value(value)
        if text is not None:
            lines.append(f"{dest.replace('_', '-')} = {text}")
    return "\n".join(lines) + "\n"


def write_effective(args: argparse.Namespace, names: Sequence[str]) -> Path | None:
    """``run.toml`` in the command's output folder (``--out``), or ``<output>.run.toml`` beside its
    output file (``-o``); None when the command writes no output."""
    out = getattr(args, "out", None)
    if out and Path(out).is_dir():
        target = Path(out) / "run.toml"
    elif getattr(args, "output", None) and Path(args.output).parent.is_dir():
        target = Path(str(args.output) + ".run.toml")
    else:
        return None
    atomic_write_text(target, effective_toml(args, names))
    return target

"""The simulated brick: the unchanged brick program on a pseudo-terminal, driving a world model.

``envi brick-sim`` (or ``python -m firmware_bridge.host.brick_sim``) prints the port to give
``envi-collect --port``. With ``--link PATH`` the port is a stable symlink that is re-pointed when
the simulated brick "reboots" after an injected disconnect, as a USB device re-enumerates.
"""

from __future__ import annotations

import argparse
import fcntl
import importlib
import os
import signal
import sys
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..brick.control import LaneKeeping
from ..brick.hardware import SimHardware
from ..brick.identity import program_hash, runtime
from ..brick.port import FdPort, LinkDown
from ..brick.program import Brick
from .faults import FaultSpec, FaultyPort

BRICK_DIR = Path(__file__).resolve().parents[1] / "brick"
DEFAULT_WORLD = "envi_py.twin:TwinWorld"


def _open_pty() -> tuple[int, int, str]:
    """A raw pty pair: the brick owns the master, the host opens the slave by name."""
    master, slave = os.openpty()
    tty.setraw(slave)
    fcntl.fcntl(master, fcntl.F_SETFL, fcntl.fcntl(master, fcntl.F_GETFL) | os.O_NONBLOCK)
    return master, slave, os.ttyname(slave)


def _point(link: Path, target: str) -> None:
    tmp = link.with_name(f".{link.name}.tmp")
    if tmp.is_symlink() or tmp.exists():
        tmp.unlink()
    tmp.symlink_to(target)
    os.replace(tmp, link)


def make_world(spec: str) -> Any:
    """``package.module:Class`` -> an instance: any world with ``reset``, ``read_color``, ``apply``."""
    module, _, attr = spec.partition(":")
    try:
        world = getattr(importlib.import_module(module), attr)()
    except (ImportError, AttributeError, TypeError) as exc:
        raise SystemExit(f"brick-sim: cannot make world {spec!r} ({exc})") from None
    missing = [m for m in ("reset", "read_color", "apply") if not callable(getattr(world, m, None))]
    if missing:
        raise SystemExit(f"brick-sim: world {spec} has no {', '.join(missing)}")
    return world


def serve(
    world: Any,
    period_ms: int = 40,
    x: float = 30.0,
    threshold: float = 40.0,
    link: Path | None = None,
    faults: FaultSpec | None = None,
    journal: Path | None = None,
    seed: int = 0,
    announce: Callable[[str], None] = print,
) -> None:
    """Run the simulated brick in ``world`` until interrupted; a disconnect starts it over on a new pty."""
    log = open(journal, "a") if journal else None
    disconnected = False
    try:
        while True:
            master, slave, path = _open_pty()
            if link is not None:
                _point(link, path)
            announce(str(link or path))
            port: FdPort | FaultyPort = FdPort(master)
            if faults is not None or log is not None:  # a journal alone is a port without faults
                port = FaultyPort(port, faults or FaultSpec(), log, disconnected)
            brick = Brick(
                port,
                SimHardware(world, seed),
                LaneKeeping(x, threshold),
                period_ms,
                program_hash(str(BRICK_DIR)),
                runtime() + " (simulated brick)",
            )
            try:
                brick.serve_forever()
            except LinkDown as exc:
                print(f"brick-sim: link down ({exc}); starting over", file=sys.stderr, flush=True)
                disconnected = True
            finally:
                os.close(master)
                os.close(slave)
    finally:
        if log is not None:
            log.close()
        if link is not None and link.is_symlink():
            link.unlink()


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--period", type=int, default=40, help="loop period in ms (default 40: 25 Hz)")
    p.add_argument("--x", type=float, default=30.0, help="lane-keeping steering angle x (default 30)")
    p.add_argument("--threshold", type=float, default=40.0, help="lane-keeping threshold (default 40)")
    p.add_argument("--link", type=Path, help="also make this symlink to the pty (stable across restarts)")
    p.add_argument(
        "--faults",
        type=FaultSpec.parse,
        help="inject faults, e.g. 'garbage=0.02,flip=0.01,drop=0.01,dup=0.01,rx_drop=0.01,disconnect=300,seed=1'",
    )
    p.add_argument(
        "--journal", type=Path, help="write one line per frame sent (for tests; with --faults, what each fault did)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated world (run r uses seed*65536+r)")
    p.add_argument(
        "--world",
        default=DEFAULT_WORLD,
        help="the world as package.module:Class "
        f"(default {DEFAULT_WORLD}, the physics twin; firmware_bridge.host.world:EdgeWorld "
        "is a small stand-in)",
    )


def run_args(args: argparse.Namespace) -> int:
    def announce(path: str) -> None:
        print(path, flush=True)

    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # clean up the symlink on kill too
    try:
        serve(
            make_world(args.world),
            args.period,
            args.x,
            args.threshold,
            args.link,
            args.faults,
            args.journal,
            args.seed,
            announce,
        )
    except KeyboardInterrupt:
        return 0
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``brick-sim`` to an ``argparse`` subcommand set (``envi brick-sim``); sets ``func``."""
    p = subparsers.add_parser("brick-sim", help="run the simulated brick on a pseudo-terminal", description=__doc__)
    add_arguments(p)
    p.set_defaults(func=run_args)
    return p


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="brick-sim", description=__doc__)
    add_arguments(p)
    return run_args(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

"""``envi-export``: the command line of :mod:`envi_py.export`, kept apart so that ``--help`` and
argument errors answer at once (torch and onnx are imported only once there is a model to export)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from .cli_parser import EnviParser
from .interrupt import exit_code, signals_interrupt
from .notes import one_line

if TYPE_CHECKING:
    from .model import Checkpoint


def main(argv: list[str] | None = None) -> int:
    ap = EnviParser(prog="envi-export", description="Export an envi checkpoint to ONNX for the C++ runtime.")
    ap.add_argument("model", help="envi checkpoint (.pt)")
    ap.add_argument("-o", "--output", required=True, help="ONNX file to write; an existing file there is replaced")
    ap.add_argument("--no-check", action="store_true", help="skip the onnxruntime parity check")
    ap.add_argument(
        "--layers",
        default=None,
        help="effect layers file (as envi diagnose writes it): embedded, so envi_sim and the native engine "
        "simulate the model with them",
    )
    ap.add_argument(
        "--member",
        type=int,
        default=None,
        help="of a seed ensemble (envi train --members), the member to export (0..K-1): a file holds one "
        "network; envi_sim --model m0.onnx m1.onnx ... runs the exported members as the ensemble",
    )
    args = ap.parse_args(argv)
    try:
        with signals_interrupt():  # a kill removes the temporary file, as Ctrl-C does
            path, ckpt = _export(args)
    except ValueError as exc:
        print(f"envi-export: error: {one_line(str(exc)) or type(exc).__name__}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        print(f"envi-export: interrupted; {args.output} is left as it was", file=sys.stderr)
        return exit_code(exc)
    from .effect_layers import describe
    from .export import OPSET, PARITY_TOL

    size = path.stat().st_size
    print(
        f"wrote {path} ({size / 1024:.1f} KiB, opset {OPSET}, {ckpt.config.head} head"
        + ("" if args.no_check else f", onnxruntime parity <= {PARITY_TOL:g}")
        + (f", effect layers: {describe(ckpt.layers)}" if ckpt.layers else "")
        + ")"
    )
    return 0


def _export(args: argparse.Namespace) -> tuple[Path, Checkpoint]:
    """The checkpoint (one member of an ensemble, with its effect layers) written to ONNX."""
    from .effect_layers import read_layers
    from .export import export
    from .files import refuse_overwriting
    from .model import Checkpoint

    refuse_overwriting([args.output], [args.model, args.layers], "-o")
    ckpt = Checkpoint.load(args.model)
    if args.member is not None:
        ckpt = ckpt.member(args.member)
    elif ckpt.members:
        raise ValueError(
            f"{args.model}: a seed ensemble of {ckpt.size} members; an ONNX file holds one: "
            f"export each with --member 0..{ckpt.size - 1}"
        )
    if args.layers:
        ckpt = ckpt.with_layers(read_layers(args.layers))
    return export(ckpt, args.output, check=not args.no_check), ckpt


if __name__ == "__main__":
    raise SystemExit(main())

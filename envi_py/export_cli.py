"""``envi-export``: the command line of :mod:`envi_py.export`, kept apart so that ``--help`` and
argument errors answer at once (torch and onnx are imported only once there is a model to export)."""

from __future__ import annotations

import sys

from .cli_parser import EnviParser


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
    args = ap.parse_args(argv)
    from .effect_layers import describe, read_layers
    from .export import OPSET, PARITY_TOL, export
    from .model import Checkpoint

    try:
        ckpt = Checkpoint.load(args.model)
        if args.layers:
            ckpt = ckpt.with_layers(read_layers(args.layers))
        path = export(ckpt, args.output, check=not args.no_check)
    except ValueError as exc:
        print(f"envi-export: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    size = path.stat().st_size
    print(
        f"wrote {path} ({size / 1024:.1f} KiB, opset {OPSET}, {ckpt.config.head} head"
        + ("" if args.no_check else f", onnxruntime parity <= {PARITY_TOL:g}")
        + (f", effect layers: {describe(ckpt.layers)}" if ckpt.layers else "")
        + ")"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

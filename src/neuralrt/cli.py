"""Command line: thin wrappers that parse arguments, call `neuralrt.api`, and print.

Bad input ends with one line on stderr (``neuralrt: error: ...``) and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import __version__, api
from .errors import NeuralRTError


def _print_result(result: dict, as_json: bool) -> None:
    if as_json:
        print(json.dumps(result, indent=None, default=float))
        return
    for key, value in result.items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, dict):
            value = ", ".join(f"{k}={v:.6g}" if isinstance(v, float) else f"{k}={v}" for k, v in value.items())
        print(f"{key:>24}: {value}")


# --- commands -----------------------------------------------------------------------------------


def _cmd_compare(args) -> None:
    _print_result(api.compare(args.reference, args.test, heatmap=args.heatmap, hdr=args.hdr), args.json)


def _cmd_info(args) -> None:
    _print_result(api.info(args.path), args.json)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="neuralrt",
        description="Neural ray intersection (LSNIF, N-BVH, NIF) beside exact Embree ray tracing.",
    )
    parser.add_argument("--version", action="version", version=f"neuralrt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("compare", help="FLIP, PSNR and relMSE of a test image against a reference")
    p.add_argument("reference", help="reference image (EXR, PNG, JPG, HDR)")
    p.add_argument("test", help="test image of the same size")
    p.add_argument("--heatmap", metavar="PNG", help="write the FLIP error map (magma) here")
    p.add_argument("--hdr", action="store_true", help="HDR-FLIP on linear values (default: LDR-FLIP on clamped sRGB)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser("info", help="triangles, bounds and BVH A/B bytes of a mesh; summary of a scene or model")
    p.add_argument("path", help="mesh file, scene file / builtin:NAME, or model file (.nrt)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_info)

    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        args.func(args)
    except NeuralRTError as exc:
        print(f"neuralrt: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("neuralrt: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

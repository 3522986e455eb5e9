"""``mlv-ros``: the command-line front end.

Each subcommand lives in ``mlv_ros.tools.<name>`` and exposes ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their subcommand runs, so a broken or slow
import in one never affects another.
"""

from __future__ import annotations

import argparse
import importlib
import sys

SUBCOMMANDS = {
    "demo": ("mlv_ros.tools.demo", "run the whole pipeline on the built-in normal phantom"),
    "run": ("mlv_ros.tools.run", "run the graph on DICOM, a phantom preset or a bag"),
    "simulate": ("mlv_ros.tools.simulate", "write a simulated tagged-MRI study (DICOM + ground truth)"),
    "report": ("mlv_ros.tools.report", "build the motion report from a recorded run"),
    "recover": ("mlv_ros.tools.recover", "rewrite a valid MCAP from a damaged one"),
    "bench": ("mlv_ros.tools.bench", "run benchmarks (JSON to stdout)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mlv-ros", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        try:
            importlib.import_module(module).add_arguments(p)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            p.set_defaults(_missing=True)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "_missing", False):
        print(f"mlv-ros {args.command}: not available in this version", file=sys.stderr)
        return 2
    return int(importlib.import_module(args._module).run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())

"""``mlv-ros recover DAMAGED.mcap OUT.mcap``: rewrite a valid recording from one whose writer was
killed (every message of every complete chunk is kept; see :func:`mlv_ros.bagio.recover`)."""

from __future__ import annotations

import json
import sys


def add_arguments(parser):
    parser.add_argument("damaged", help="the damaged MCAP file")
    parser.add_argument("out", help="the recovered MCAP file to write (must not exist)")


def run(args) -> int:
    from mlv_ros.bagio import recover

    try:
        result = recover(args.damaged, args.out)
    except (FileNotFoundError, FileExistsError) as exc:
        print(f"mlv-ros recover: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result, indent=2))
    return 0 if result["messages"] else 1

# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
``mlv-ros recover DAMAGED.mcap OUT.mcap``: rewrite a valid recording from a damaged one.

DAMAGED is a recording whose writer was killed; every message of every complete chunk is kept (see
:func:`mlv_ros.bagio.recover`).

DAMAGED may be a run directory holding one ``.mcap`` file.
"""

from __future__ import annotations

import json
from pathlib import Path
import sys

from mlv_ros.cli import describe_os_error, one_line


def add_arguments(parser):
    parser.add_argument('damaged', help='the damaged MCAP file (or the run directory holding it)')
    parser.add_argument('out', help='the recovered MCAP file to write (must not exist)')


def _fail(msg) -> int:
    print(f'mlv-ros recover: {one_line(msg)}', file=sys.stderr)
    return 2


def _source(damaged: Path) -> Path:
    """Return the file to read (DAMAGED, or the one .mcap in a directory); ValueError otherwise."""
    if not damaged.exists():
        raise ValueError(
            f'{damaged} does not exist: give the damaged recording (e.g. RUN_DIR/run.mcap)'
        )
    if not damaged.is_dir():
        return damaged
    found = sorted(damaged.glob('*.mcap'))
    if len(found) == 1:
        return found[0]
    if not found:
        raise ValueError(
            f'{damaged} is a directory with no .mcap file in it: give the damaged recording itself'
        )
    raise ValueError(
        f'{damaged} holds {len(found)} .mcap files: give the one to recover, e.g. {found[0]}'
    )


def run(args) -> int:
    from mlv_ros.bagio import recover

    out = Path(args.out)
    try:
        src = _source(Path(args.damaged))
    except ValueError as exc:
        return _fail(exc)
    if out.exists():
        what = 'a directory' if out.is_dir() else 'a file'
        suggestion = (
            out / 'recovered.mcap' if out.is_dir() else out.with_name(out.stem + '-recovered.mcap')
        )
        return _fail(
            f'{out} exists ({what}): give a new file name for the recovered recording, '
            f'e.g. {suggestion}'
        )
    try:
        result = recover(src, out)
    except OSError as exc:
        return _fail(describe_os_error(exc))
    print(json.dumps(result, indent=2))
    if not result['messages']:
        # Nothing worth keeping: an empty file would only block the next attempt at this name.
        out.unlink(missing_ok=True)
        print(
            f'mlv-ros recover: no message could be read from {src} '
            f'({one_line(result.get("stopped_at", ""))}); '
            'is it an MCAP recording?',
            file=sys.stderr,
        )
        return 1
    return 0

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
``mlv-ros report RUN.mcap [--compare OTHER.mcap]``: the motion report of a recorded run.

Rebuilt from the recording alone (no tracking is recomputed): PNG figures in the spirit of the
paper's Fig. 9–16, a bull's-eye of peak strain by AHA segment, ``summary.json`` and an
``index.html`` that shows them together.
"""

from __future__ import annotations

from pathlib import Path
import sys

from mlv_ros.cli import describe_os_error, one_line
from mlv_ros.recording import write_report


def add_arguments(parser):
    parser.add_argument('mcap', help='recorded run (RUN_DIR/run.mcap or the run directory)')
    parser.add_argument(
        '--compare', help='a second recorded run shown side by side (e.g. hypertrophic)'
    )
    parser.add_argument('--out', help='report directory (default: RUN_DIR/report)')
    parser.add_argument(
        '--label', default=None, help='name of the run (default: its directory name)'
    )
    parser.add_argument('--compare-label', default=None, help='name of the comparison run')


def run(args) -> int:
    try:
        index = write_report(
            Path(args.mcap),
            Path(args.out) if args.out else None,
            Path(args.compare) if args.compare else None,
            args.label,
            args.compare_label,
        )
    except (FileNotFoundError, ValueError) as exc:
        print(f'mlv-ros report: {one_line(exc)}', file=sys.stderr)
        return 2
    except OSError as exc:  # mostly --out: unwritable, read-only, full
        print(
            f'mlv-ros report: cannot write the report: {describe_os_error(exc)}; '
            'choose another --out',
            file=sys.stderr,
        )
        return 2
    print(index)
    return 0

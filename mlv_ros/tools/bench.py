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

"""``mlv-ros bench NAME``: run ``bench/NAME.py`` (each prints one JSON document to stdout)."""

from __future__ import annotations

from pathlib import Path
import runpy
import sys

BENCH_DIR = Path(__file__).resolve().parents[2] / 'bench'


def available() -> list[str]:
    return sorted(p.stem for p in BENCH_DIR.glob('*.py') if not p.stem.startswith('_'))


def add_arguments(parser):
    parser.add_argument('name', help="benchmark name (a file in bench/), or 'all'")
    parser.add_argument('extra', nargs='*', help='arguments passed to the benchmark')


def run(args) -> int:
    names = available() if args.name == 'all' else [args.name]
    for name in names:
        path = BENCH_DIR / f'{name}.py'
        if name not in available():  # a name, never a path: "../x" must not run another script
            print(
                f'mlv-ros bench: no benchmark {name!r}; choose one of: all, '
                f'{", ".join(available())}',
                file=sys.stderr,
            )
            return 2
        sys.argv = [str(path), *args.extra]
        try:
            runpy.run_path(str(path), run_name='__main__')
        except SystemExit as exc:
            if exc.code not in (None, 0):
                return int(exc.code) if isinstance(exc.code, int) else 1
    return 0

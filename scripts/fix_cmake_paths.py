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
Rewrite the wheel builder's baked include paths in the venv's cmake files.

Some ``share/*/cmake/*.cmake`` files installed by the ``ros-jazzy-*`` wheels name the Python and
numpy include directories of the machine that built the wheels (``/opt/python/cp311-cp311/...``).
CMake refuses imported targets with non-existent include paths, so point them at this
interpreter's. Idempotent: a second run finds nothing to rewrite.

Usage: python fix_cmake_paths.py VENV
"""

from pathlib import Path
import re
import sys
import sysconfig

import numpy


def main(venv: str) -> int:
    py_include = sysconfig.get_paths()['include']
    np_include = numpy.get_include()
    # Builder paths look like /opt/python/cp311-cp311/include/python3.11 and
    # /opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/..._core/include
    np_pat = re.compile(r'/opt/python/cp311-cp311/[^\";)\s]*?/numpy/(?:_?core/)?include')
    py_pat = re.compile(r'/opt/python/cp311-cp311/include/python3\.11')
    changed = 0
    for path in Path(venv).glob('share/*/cmake/*.cmake'):
        text = path.read_text()
        new = py_pat.sub(py_include, np_pat.sub(np_include, text))
        if new != text:
            path.write_text(new)
            changed += 1
    print(f'[bootstrap] rewrote builder include paths in {changed} cmake file(s)', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1]))

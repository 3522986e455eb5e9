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

"""ament_copyright over the package's own source, as ROS's ament_python template runs it."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ['mlv_ros', 'test', 'bench', 'launch', 'setup.py', 'scripts', 'fuzz', 'bags']
# ament_copyright has no wheel on PyPI, so `make test` here skips this; a ROS install
# (rosdep key ament_copyright, declared in package.xml) runs it.
ament_copyright_main = pytest.importorskip('ament_copyright.main')


@pytest.mark.copyright
@pytest.mark.linter
def test_copyright():
    """Check that every source file carries the Apache-2.0 header ament_copyright knows."""
    rc = ament_copyright_main.main(argv=[str(REPO / s) for s in SOURCES])
    assert rc == 0, 'Found errors'

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

"""ament_pep257 over the package's own source, as ROS's ament_python template runs it."""

from pathlib import Path

from ament_pep257.main import main
import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ['mlv_ros', 'test', 'bench', 'launch', 'setup.py', 'scripts', 'fuzz', 'bags']


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    """Check the docstrings against ament's convention, nothing skipped."""
    rc = main(argv=[str(REPO / s) for s in SOURCES])
    assert rc == 0, 'Found code style errors / warnings'

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

"""ament_flake8 over the package's own source, as ROS's ament_python template runs it."""

import configparser
from pathlib import Path

import ament_flake8
from ament_flake8.main import main_with_errors
import ament_pep257.main
import flake8_docstrings
import pydocstyle
import pytest

REPO = Path(__file__).resolve().parents[1]
# The package's own Python source; not .venv, build/ or the generated mlv_msgs code (in .venv).
SOURCES = ['mlv_ros', 'test', 'bench', 'launch', 'setup.py', 'scripts', 'fuzz', 'bags']


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch, tmp_path):
    """Check the source against ament's own flake8 configuration, nothing skipped."""
    # The docstring codes (flake8-docstrings: pydocstyle run per file in flake8's processes) are
    # checked by test_pep257 over the same files with the same pydocstyle: leave them out here
    # (~8 of this test's ~40 s of CPU) only while every code they would check is among those.
    ini = configparser.ConfigParser()
    ini.read(Path(ament_flake8.__file__).parent / 'configuration' / 'ament_flake8.ini')
    ignored = {c.strip() for c in ini['flake8']['extend-ignore'].split(',')}
    docstring_codes = pydocstyle.conventions['pep257'] - ignored  # the plugin's default convention
    pep257_codes = set(pydocstyle.violations.ErrorRegistry.get_error_codes()) - set(
        ament_pep257.main._ament_ignore
    )
    assert docstring_codes and docstring_codes <= pep257_codes, docstring_codes - pep257_codes
    monkeypatch.setattr(flake8_docstrings.pep257Checker, 'off_by_default', True, raising=False)
    # ament_flake8 walks the working directory for AMENT_IGNORE markers: not the whole .venv
    monkeypatch.chdir(tmp_path)
    rc, errors = main_with_errors(argv=[str(REPO / s) for s in SOURCES])
    assert rc == 0, 'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)

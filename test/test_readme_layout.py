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
The README's layout table names every folder, every package module and every core part.

A row's path (its first cell) must exist; every top-level folder git tracks has a row; every
module of ``mlv_ros`` and every module or package of ``mlv_ros/core`` is named in a row, by its
path or, as the runner's helpers and the core's parts are, in backquotes in the row's text.
"""

from pathlib import Path
import re
import subprocess

import pytest

ROOT = Path(__file__).resolve().parents[1]


def layout_rows() -> dict[str, str]:
    """Return the README's layout table as {path: the row's text}."""
    text = (ROOT / 'README.md').read_text()
    section = text.split('\n## Layout\n', 1)[1].split('\n## ', 1)[0]
    rows = {}
    for line in section.splitlines():
        m = re.match(r'\| `([^`]+)` \| (.*) \|$', line)
        if m:
            rows[m.group(1)] = m.group(2)
    return rows


def tracked_folders() -> set[str]:
    """Return the top-level folders git tracks files in (skip outside a git checkout)."""
    try:
        out = subprocess.run(
            ['git', 'ls-files'], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip('not a git checkout: no tracked files to compare')
    return {name.split('/')[0] for name in out.splitlines() if '/' in name}


def test_every_row_names_a_path_that_exists():
    rows = layout_rows()
    assert len(rows) > 10, 'the layout table was not found'
    assert [p for p in rows if not (ROOT / p).exists()] == []


def test_every_folder_has_a_row():
    rows = layout_rows()
    folders = sorted(tracked_folders())
    assert [f for f in folders if not any(p.startswith(f + '/') for p in rows)] == []


def test_every_module_and_core_part_is_named():
    rows = layout_rows()
    named = set(rows) | {name for text in rows.values() for name in re.findall(r'`([^`]+)`', text)}
    package = ROOT / 'mlv_ros'
    modules = [p.name for p in package.glob('*.py') if p.name != '__init__.py']
    assert [m for m in modules if f'mlv_ros/{m}' not in named and m not in named] == []
    core = rows['mlv_ros/core/']
    parts = [p.stem for p in (package / 'core').iterdir() if not p.name.startswith('_')]
    assert [p for p in sorted(set(parts)) if f'`{p}`' not in core] == []

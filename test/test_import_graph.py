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
The package's import graph follows the data flow: no node imports a node, no tool a tool.

Every import in every module (at the top or inside a function) is read with ``ast``. A node
module (``mlv_ros/nodes/*``, but ``common``: the helper every node shares) imports no other node
module: what two nodes share (message schemas, stream policy) lives in ``conversions``,
``core`` or ``nodes/common``. A tool module (``mlv_ros/tools/*``, one per ``mlv-ros``
subcommand) imports no other tool module: shared pieces (running the graph, reading a run) live
outside ``tools/``. ``core`` imports neither rclpy nor a message package. Synthetic truth
(``core/sim``: phantoms, analytic scenes, a run's accuracy against them) is out of the estimating
core's reach: only the frame source, the tools, reading a run and ``core/io`` (which writes a
phantom's truth beside its images) import it.
"""

import ast
from pathlib import Path
import subprocess
import sys

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'mlv_ros'
SHARED = {'mlv_ros.nodes.common', 'mlv_ros.nodes', 'mlv_ros.tools'}


def module_name(path: Path) -> str:
    """Return the dotted module name of a file under the package."""
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def imports(path: Path) -> set[str]:
    """
    Return the modules the file at ``path`` imports, as absolute names.

    Relative imports are resolved; ``from x import y`` gives both ``x`` and ``x.y``.
    """
    package = module_name(path)
    if path.name != '__init__.py':
        package = package.rpartition('.')[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                up = package.split('.')[: len(package.split('.')) - node.level + 1]
                base = '.'.join(up + ([base] if base else []))
            found.add(base)
            found.update(f'{base}.{a.name}' for a in node.names)
    return found


def graph() -> dict[str, set[str]]:
    """Return {module: the package modules it imports}."""
    modules = {module_name(p): p for p in PACKAGE.rglob('*.py')}
    return {m: {i for i in imports(p) if i in modules} for m, p in modules.items()}


def arrows(within: str) -> list[str]:
    """Return the imports from a module under ``within`` to another there (shared ones allowed)."""
    prefix = f'mlv_ros.{within}.'
    return sorted(
        f'{src} -> {dst}'
        for src, dsts in graph().items()
        if src.startswith(prefix) and src not in SHARED
        for dst in dsts
        if dst.startswith(prefix) and dst not in SHARED and dst != src
    )


def test_the_walk_sees_imports_inside_functions():
    # The tools import lazily (inside functions); the walk must see those too.
    g = graph()
    assert 'mlv_ros.nodes.common' in g['mlv_ros.nodes.tag_detector']
    assert any(dst.startswith('mlv_ros.nodes.') for dst in g['mlv_ros.runner'])
    assert 'mlv_ros.core.sim' in g['mlv_ros.tools.demo']  # imported inside run()


@pytest.mark.parametrize('within', ['nodes', 'tools'])
def test_no_arrow_between_two_nodes_or_two_tools(within):
    assert arrows(within) == []


def test_core_imports_no_ros():
    ros = sorted(
        f'{module_name(p)} -> {i}'
        for p in (PACKAGE / 'core').rglob('*.py')
        for i in imports(p)
        if i.split('.')[0] in ('rclpy', 'rosbag2_py') or i.endswith('.msg')
    )
    assert ros == []


# Who may import synthetic truth: the phantom frame source and the process that renders its
# frames, the tools, reading a run (accuracy against a phantom) and core/io's ground-truth files.
SIM_USERS = ('mlv_ros.core.sim', 'mlv_ros.core.io.', 'mlv_ros.nodes.frame_source',
             'mlv_ros.render_process', 'mlv_ros.tools.', 'mlv_ros.recording')


def test_only_the_sources_of_truth_import_the_simulators():
    found = sorted(
        f'{src} -> {dst}'
        for src, dsts in graph().items()
        if not src.startswith(SIM_USERS)
        for dst in dsts
        if dst == 'mlv_ros.core.sim' or dst.startswith('mlv_ros.core.sim.')
    )
    assert found == []
    assert 'mlv_ros.core.sim.evaluation' in graph()['mlv_ros.recording']  # the walk sees them


def test_the_tag_detector_imports_no_registration_or_dicom_reader():
    # Its process imports only what it runs (its start is on the study's critical path): the
    # registration package's names come from their submodules on first use.
    code = (
        'import sys, mlv_ros.nodes.tag_detector; '
        'print([m for m in ("mlv_ros.core.registration.register", "pydicom") if m in sys.modules])'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True)
    assert out.stdout.split('\n')[-2] == '[]', out.stdout
    from mlv_ros.core import registration

    assert registration.register_ed.__module__ == 'mlv_ros.core.registration.register'
    with pytest.raises(AttributeError, match='no attribute'):
        registration.no_such_name

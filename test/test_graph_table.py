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
The one table of the graph (mlv_ros/graph_table.py) against the code it stands for.

Each node's module has the class and the ``main()`` the table names; every topic is one of
``mlv_ros.qos``'s; each topic a node takes is put out by another node of a run, and setup.py's
console scripts are the table's nodes.
"""

import importlib
from pathlib import Path
import runpy
import sys
import types

from mlv_ros import graph_table, qos
import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize('entry', graph_table.NODES, ids=lambda e: e.name)
def test_each_entry_names_its_module_class_and_topics(entry):
    module = importlib.import_module(f'mlv_ros.nodes.{entry.name}')
    assert callable(module.main) and isinstance(getattr(module, entry.node_class), type)
    assert set(entry.subscribes) | set(entry.publishes) <= set(qos.TOPIC_TYPES)


def test_every_input_of_a_run_is_some_run_node_output():
    run = [n for n in graph_table.NODES if n.in_run]
    out = {t for n in run for t in n.publishes} | {qos.DIAGNOSTICS}
    assert {t for n in run for t in n.subscribes} <= out
    assert graph_table.RUN_NODES[-1] == 'frame_source'  # the source starts last


def test_setup_py_console_scripts_are_the_table(monkeypatch):
    # setup() only records its arguments: nothing is built or installed.
    seen = {}
    fake = types.SimpleNamespace(setup=lambda **kw: seen.update(kw), find_packages=lambda **kw: [])
    monkeypatch.setitem(sys.modules, 'setuptools', fake)
    runpy.run_path(str(REPO / 'setup.py'))
    scripts = seen['entry_points']['console_scripts']
    assert scripts == [f'{n.name} = mlv_ros.nodes.{n.name}:main' for n in graph_table.NODES] + [
        'mlv-ros = mlv_ros.cli:main'
    ]

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
launch/pipeline.launch.py without ROS's launch tools, against stand-ins.

launch/pipeline.launch.py without ROS's launch tools (launch and launch_ros are not on PyPI):
its declared arguments read from its source, its own code run against stand-ins for launch,
launch_ros and ament_index_python, and what it makes of the arguments
(:mod:`mlv_ros.launch_settings`).
"""

import ast
import importlib.util
import sys
import time
import types

from conftest import REPO
from mlv_ros.launch_settings import fresh_run_dir, graph_settings
import pytest

LAUNCH_FILE = REPO / 'launch' / 'pipeline.launch.py'
ARGUMENTS = {'source', 'path', 'output_dir', 'namespace', 'params_file', 'live', 'live_port'}
GRAPH = {
    'recorder',
    'motion_analyzer',
    'meshless_solver',
    'registration',
    'tag_detector',
    'frame_source',
}


def test_launch_file_declares_its_arguments():
    tree = ast.parse(LAUNCH_FILE.read_text(), filename=str(LAUNCH_FILE))
    declared = {}
    for call in ast.walk(tree):
        if (
            isinstance(call, ast.Call)
            and getattr(call.func, 'id', None) == 'DeclareLaunchArgument'
        ):
            declared[call.args[0].value] = {k.arg: k.value for k in call.keywords}
    assert set(declared) == ARGUMENTS
    assert all('description' in kw and 'default_value' in kw for kw in declared.values())
    assert declared['output_dir']['default_value'].value == ''  # empty: a fresh run directory
    assert [e.value for e in declared['source']['choices'].elts] == ['phantom', 'dicom', 'bag']
    assert declared['live']['default_value'].value == 'false'  # the live view only when asked for


class _Recorded:
    """A stand-in for a launch action: keeps what it was given."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context.launch_configurations[self.name]


@pytest.fixture
def launch_file(monkeypatch):
    """Import the launch file as a module against stand-ins for launch and launch_ros."""
    fakes = {
        'launch': {'LaunchDescription': lambda entities: list(entities)},
        'launch.actions': {'DeclareLaunchArgument': _Recorded, 'OpaqueFunction': _Recorded},
        'launch.substitutions': {'LaunchConfiguration': _LaunchConfiguration},
        'launch_ros': {},
        'launch_ros.actions': {'Node': _Recorded},
        'ament_index_python.packages': {
            'get_package_share_directory': lambda pkg: f'/opt/share/{pkg}'
        },
    }
    for name, attrs in fakes.items():
        monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attrs))
    spec = importlib.util.spec_from_file_location('pipeline_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _launch(module, **given):
    """Return the nodes the launch file starts for ``given`` arguments (the rest at defaults)."""
    entities = module.generate_launch_description()
    config = {
        a.args[0]: a.kwargs['default_value']
        for a in entities
        if a.args and 'default_value' in a.kwargs
    }
    config.update(given)
    setup = next(a for a in entities if 'function' in a.kwargs).kwargs['function']
    return {
        n.kwargs['name']: n.kwargs
        for n in setup(types.SimpleNamespace(launch_configurations=config))
    }


def test_each_launch_records_to_a_fresh_run_directory(launch_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    first, second = _launch(launch_file), _launch(launch_file)  # two launches from one directory
    assert set(first) == GRAPH and all(n['namespace'] is None for n in first.values())
    outputs = [nodes['recorder']['parameters'][1]['output'] for nodes in (first, second)]
    assert outputs[0] != outputs[1], outputs
    for out in outputs:
        run_dir = tmp_path / 'runs' / out.split('/runs/')[1].removesuffix('/run.mcap')
        assert run_dir.is_dir() and not any(run_dir.iterdir())
    assert first['frame_source']['parameters'] == [
        '/opt/share/mlv_ros/config/graph.yaml',
        {'source': 'phantom'},
    ]


def test_launch_arguments_reach_the_nodes(launch_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    nodes = _launch(
        launch_file,
        source='dicom',
        path='data/study',
        output_dir='out/r1',
        namespace='study2',
        params_file='/etc/mine.yaml',
    )
    assert {n['namespace'] for n in nodes.values()} == {'/study2'}
    src = nodes['frame_source']['parameters']
    assert (
        src[0] == '/etc/mine.yaml'
        and src[1]['source'] == 'dicom'
        and src[1]['path'] == str(tmp_path / 'data/study')
    )
    assert nodes['recorder']['parameters'][1]['output'] == str(
        tmp_path / 'out' / 'r1' / 'run.mcap'
    )
    assert all(n['parameters'][1]['diagnostic_updater.use_fqn'] is True for n in nodes.values())


def test_live_argument_adds_the_live_view(launch_file, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    nodes = _launch(launch_file, live='true', live_port='9000', namespace='study2')
    assert set(nodes) == GRAPH | {'live_view'}
    view = nodes['live_view']
    assert view['executable'] == 'live_view' and view['namespace'] == '/study2'
    assert (
        view['parameters'][1]['port'] == 9000
        and view['parameters'][1]['diagnostic_updater.use_fqn'] is True
    )


def test_launch_settings_refuse_what_cannot_work(tmp_path):
    (tmp_path / 'old').mkdir()
    (tmp_path / 'old' / 'run.mcap').write_bytes(b'')
    for kwargs, words in (
        ({'source': 'camera'}, 'is not one of phantom, dicom, bag'),
        ({'source': 'bag'}, 'needs path:='),
        ({'namespace': '2nd study'}, 'is not a ROS namespace'),
        ({'output_dir': 'old'}, 'already holds a run'),
    ):
        with pytest.raises(ValueError, match=words):
            graph_settings(cwd=tmp_path, **kwargs)
    assert not (tmp_path / 'runs').exists()  # nothing created for a refused launch
    # Two launches in the same second get two directories.
    stem = time.strftime('%Y%m%d-%H%M%S', time.localtime(0))
    assert [fresh_run_dir(tmp_path / 'runs', now=0).name for _ in range(2)] == [stem, f'{stem}-2']

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
Shared test harness: ROS isolation and bounded spinning.

Each pytest process claims its own ROS_DOMAIN_ID (``mlv_ros.domain``: an flock on a per-id file,
so concurrent test runs on one machine never share a domain) and restricts discovery to localhost,
before rclpy is used anywhere. Tests get a fresh rclpy Context and executor per test and wait on
conditions with ``spin_until`` — never a bare sleep.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys
import time

from mlv_ros.domain import claim_domain_id
import pytest

REPO = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix)


os.environ['ROS_DOMAIN_ID'] = str(claim_domain_id())
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('AMENT_PREFIX_PATH', str(VENV))
os.environ.setdefault('MPLBACKEND', 'Agg')
# Graph runs keep every node in the run's process unless a test asks for the default layout
# (`default_layout`): the same nodes over the same DDS, each hop serialized, at ~20-28 % less CPU
# a run (two process start-ups and their pipes), which keeps `make test` within its 10 minutes on
# 2 cores. The layout itself (the tag detector's and the renderer's processes: killed,
# restarted, signalled, their memory) is tested where it matters, with the fixture.
os.environ.setdefault('MLV_ROS_ONE_PROCESS', '1')


# The longest modules, longest first: their share of the suite's time (`pytest --durations=0`
# summed per module, one whole run on the 2-core host; docs/benchmarks.md).
LONGEST = (
    'test_random_protocol_graph',  # 11 %: four studies simulated and run
    'test_pipeline_graph',  # 8 %
    'test_tags_grid_estimate',  # 8 %
    'test_calm_console',  # 6 %
    'test_run_interrupt',  # 6 %
    'test_tracking',  # 6 %
    'test_flake8',  # 5 % (on both cores)
    'test_dicom_study_selection',  # 4 %
    'test_registration_pipeline',  # 4 %
    'test_report_build',  # 3 %
    'test_tags_tracker',  # 3 %
    'test_dicom_properties',  # 2.5 %
)


def pytest_collection_modifyitems(config, items):
    """
    Order the modules longest first, each module's tests kept together.

    pytest-xdist (``-n 3 --dist loadfile``, pytest.ini) hands whole modules to its workers in
    this order: the :data:`LONGEST` ones in their order, then the other modules with a ``slow``
    test, then the rest. Longest first, the many short modules fill in at the end and the
    workers finish together.
    """
    rank = {name: i for i, name in enumerate(LONGEST)}
    slow = {item.module.__name__ for item in items if item.get_closest_marker('slow')}

    def key(item):
        name = item.module.__name__
        return (rank.get(name, len(rank)), name not in slow)

    items.sort(key=key)  # stable: modules stay whole, in collection order within a rank


@pytest.fixture
def ros_context():
    """Yield a fresh, initialised rclpy Context, shut down after the test."""
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


@pytest.fixture
def executor(ros_context):
    """Yield a single-threaded executor on ``ros_context``; its nodes are destroyed after."""
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor(context=ros_context)
    yield ex
    for node in list(ex.get_nodes()):
        ex.remove_node(node)
        node.destroy_node()
    ex.shutdown()


def spin_until(executor, predicate, timeout: float = 10.0, step: float = 0.05) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout`` seconds pass; returns it."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step)
    return bool(predicate())


@pytest.fixture
def spin():
    return spin_until


def console_script(name: str) -> str:
    """Path of one of our console scripts in the running venv."""
    path = VENV / 'bin' / name
    if not path.exists():
        pytest.fail(f'console script {name} is not installed in {VENV}/bin (run make bootstrap)')
    return str(path)


@pytest.fixture
def default_layout(monkeypatch):
    """Run graphs as a user's run does: the tag detector and renderer in processes of their own."""
    monkeypatch.delenv('MLV_ROS_ONE_PROCESS', raising=False)

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
Recordings as rosbag2 Jazzy writes them, replay with /clock, and package.xml for rosdep.

The expected format is written here from rosbag2's own source, branch ``jazzy`` of
github.com/ros2/rosbag2 (commit 64717ee8), not from our writer:

* ``rosbag2_storage/include/rosbag2_storage/yaml.hpp``: ``convert<BagMetadata>``,
  ``convert<TopicInformation>``, ``convert<TopicMetadata>`` (version >= 9: ``offered_qos_profiles``
  decoded as a *sequence*, a string is refused), ``convert<FileInformation>``, times as
  ``{nanoseconds}`` / ``{nanoseconds_since_epoch}``;
* ``rosbag2_storage/src/rosbag2_storage/qos.cpp``: ``convert<rclcpp::QoS>::encode`` (keys and
  their order; policies by name from version 9; ``rmw_time_t`` as ``{sec, nsec}``);
* ``rosbag2_storage_mcap/src/mcap_storage.cpp``: channel metadata ``offered_qos_profiles`` and
  ``topic_type_hash``; ``update_metadata`` writes a metadata record named ``rosbag2`` with the one
  key ``serialized_metadata``, which ``read_metadata`` finds through the summary's metadata index;
* ``rosbag2_cpp/src/rosbag2_cpp/writers/sequential_writer.cpp``: that record is written at
  ``open`` (empty bag: starting_time = nanoseconds::max) and at ``close``.

The run is then read back by ``rosbags.rosbag2.Reader`` on the run directory (an independent
implementation that goes through metadata.yaml).
"""

from __future__ import annotations

import ast
from pathlib import Path
import re
import sys

from catkin_pkg.package import parse_package
from conftest import REPO, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from mcap.reader import make_reader
from mlv_msgs.msg import TaggedFrame
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes.frame_source import FrameSource
from mlv_ros.nodes.recorder import Recorder
from mlv_ros.nodes.replay import recorded_qos, Replay
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
import yaml

# ---------------------------------------------------------------------------- rosbag2's schema
BAG_KEYS = [
    'version',
    'storage_identifier',
    'duration',
    'starting_time',
    'message_count',
    'topics_with_message_count',
    'compression_format',
    'compression_mode',
    'relative_file_paths',
    'files',
    'custom_data',
    'ros_distro',
]  # yaml.hpp
TOPIC_INFO_KEYS = ['topic_metadata', 'message_count']  # yaml.hpp
TOPIC_KEYS = [
    'name',
    'type',
    'serialization_format',
    'offered_qos_profiles',
    'type_description_hash',
]  # yaml.hpp
FILE_KEYS = ['path', 'starting_time', 'duration', 'message_count']  # yaml.hpp
QOS_KEYS = [
    'history',
    'depth',
    'reliability',
    'durability',
    'deadline',
    'lifespan',
    'liveliness',
    'liveliness_lease_duration',
    'avoid_ros_namespace_conventions',
]  # qos.cpp
# rmw's *_to_str names (rmw/qos_string_conversions.h), which qos.cpp writes from version 9.
HISTORY = {'system_default', 'keep_last', 'keep_all', 'unknown'}
RELIABILITY = {'system_default', 'reliable', 'best_effort', 'best_available', 'unknown'}
DURABILITY = {'system_default', 'transient_local', 'volatile', 'best_available', 'unknown'}
LIVELINESS = {'system_default', 'automatic', 'manual_by_topic', 'best_available', 'unknown'}
NS_MAX = 2**63 - 1  # std::chrono::nanoseconds::max(): rosbag2's starting time before any message


def is_uint(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= 0


def check_duration(d) -> None:
    """Check an ``rmw_time_t`` as qos.cpp writes it."""
    assert isinstance(d, dict) and list(d) == ['sec', 'nsec'], d
    assert is_uint(d['sec']) and is_uint(d['nsec']) and d['nsec'] < 10**9, d


def check_qos_list(profiles) -> None:
    assert isinstance(profiles, list) and profiles, (
        f'offered_qos_profiles must be a sequence, got {profiles!r}'
    )
    for p in profiles:
        assert isinstance(p, dict) and list(p) == QOS_KEYS, p
        assert p['history'] in HISTORY and p['reliability'] in RELIABILITY, p
        assert p['durability'] in DURABILITY and p['liveliness'] in LIVELINESS, p
        assert is_uint(p['depth']) and isinstance(p['avoid_ros_namespace_conventions'], bool), p
        for key in ('deadline', 'lifespan', 'liveliness_lease_duration'):
            check_duration(p[key])


def check_bag_metadata(info: dict) -> None:
    """Field by field, what yaml.hpp's version-9 encoder writes and its decoder accepts."""
    assert list(info) == BAG_KEYS
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert list(info['duration']) == ['nanoseconds'] and is_uint(info['duration']['nanoseconds'])
    assert list(info['starting_time']) == ['nanoseconds_since_epoch']
    assert is_uint(info['starting_time']['nanoseconds_since_epoch'])
    assert is_uint(info['message_count'])
    assert isinstance(info['topics_with_message_count'], list)
    for entry in info['topics_with_message_count']:
        assert list(entry) == TOPIC_INFO_KEYS and is_uint(entry['message_count'])
        meta = entry['topic_metadata']
        assert list(meta) == TOPIC_KEYS
        assert meta['serialization_format'] == 'cdr'
        assert re.fullmatch(r'[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+', meta['type']), meta['type']
        check_qos_list(meta['offered_qos_profiles'])
        assert re.fullmatch(r'RIHS01_[0-9a-f]{64}', meta['type_description_hash'])
    # MCAP compresses chunks inside the storage plugin; rosbag2's own compression stays off.
    assert info['compression_format'] == '' and info['compression_mode'] == ''
    paths = info['relative_file_paths']
    assert isinstance(paths, list) and all(isinstance(p, str) for p in paths)
    assert [f['path'] for f in info['files']] == info['relative_file_paths']
    for f in info['files']:
        assert list(f) == FILE_KEYS and is_uint(f['message_count'])
        assert list(f['starting_time']) == ['nanoseconds_since_epoch'] and list(f['duration']) == [
            'nanoseconds'
        ]
    custom = info['custom_data']
    assert custom is None or (
        isinstance(custom, dict)
        and all(isinstance(k, str) and isinstance(v, str) for k, v in custom.items())
    )
    assert info['ros_distro'] == 'jazzy'


def rosbag2_records(path: Path) -> tuple[list[dict], set[str]]:
    """
    Return the ``rosbag2`` metadata records of an MCAP file and the names its summary indexes.

    The ``rosbag2`` metadata records of an MCAP file, in file order, and the names its summary
    indexes (rosbag2 reads the record through that index).
    """
    with open(path, 'rb') as fh:
        reader = make_reader(fh)
        records = [dict(m.metadata) for m in reader.iter_metadata() if m.name == 'rosbag2']
        summary = reader.get_summary()
    return records, {i.name for i in summary.metadata_indexes}


def channel_metadata(path: Path) -> dict[str, dict]:
    with open(path, 'rb') as fh:
        summary = make_reader(fh).get_summary()
    return {ch.topic: dict(ch.metadata) for ch in summary.channels.values()}


def log_times(path: Path) -> list[int]:
    with open(path, 'rb') as fh:
        return [m.log_time for _, _, m in make_reader(fh).iter_messages()]


# ---------------------------------------------------------------------------- recorded run
def test_recorded_run_is_a_rosbag2_jazzy_bag(ros_context, executor, tmp_path):
    run = tmp_path / 'run'
    rec = Recorder(
        context=ros_context, parameter_overrides=[Parameter('output', value=str(run / 'run.mcap'))]
    )
    src = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('num_phases', value=2),
            Parameter('wait_for_subscribers', value=1),
        ],
    )
    executor.add_node(rec)
    executor.add_node(src)
    assert spin_until(
        executor, lambda: src.done and rec.writer.topics[qos.FRAMES].count >= 4, timeout=30
    )
    rec.finish()

    # metadata.yaml, field by field
    text = (run / 'metadata.yaml').read_text()
    doc = yaml.safe_load(text)
    assert list(doc) == ['rosbag2_bagfile_information']
    # laid out as yaml-cpp emits it: the profiles a block sequence under their key, not a string
    assert re.search(r'\n {8}offered_qos_profiles:\n {10}- history: keep_last\n {12}depth: ', text)
    info = doc['rosbag2_bagfile_information']
    check_bag_metadata(info)
    assert info['relative_file_paths'] == ['run.mcap']
    topics = {e['topic_metadata']['name']: e for e in info['topics_with_message_count']}
    assert set(topics) == set(qos.TOPIC_TYPES)  # every recorded topic, messages or not
    assert topics[qos.FRAMES]['message_count'] == 4
    for name, entry in topics.items():
        assert entry['topic_metadata']['type'] == qos.TOPIC_TYPES[name]
        p = entry['topic_metadata']['offered_qos_profiles'][0]
        expected = qos.qos_dict(qos.topic_qos(name))
        assert {k: p[k] for k in expected} == expected
    frames_qos = topics[qos.FRAMES]['topic_metadata']['offered_qos_profiles'][0]
    assert (
        frames_qos['durability'] == 'transient_local' and frames_qos['depth'] == qos.STREAM_DEPTH
    )
    assert frames_qos['deadline'] == {
        'sec': 9223372036,
        'nsec': 854775807,
    }  # RMW_DURATION_INFINITE
    # times and counts agree with the messages in the file
    times = log_times(run / 'run.mcap')
    assert info['message_count'] == len(times) == sum(e['message_count'] for e in topics.values())
    assert info['starting_time']['nanoseconds_since_epoch'] == min(times)
    assert info['duration']['nanoseconds'] == max(times) - min(times)
    assert info['files'] == [
        {
            'path': 'run.mcap',
            'starting_time': info['starting_time'],
            'duration': info['duration'],
            'message_count': len(times),
        }
    ]

    # MCAP: channel metadata and the rosbag2 record (written at open, and final at close)
    for name, meta in channel_metadata(run / 'run.mcap').items():
        assert set(meta) == {'offered_qos_profiles', 'topic_type_hash'}
        assert isinstance(meta['offered_qos_profiles'], str)  # MCAP metadata is a string map
        assert (
            yaml.safe_load(meta['offered_qos_profiles'])
            == topics[name]['topic_metadata']['offered_qos_profiles']
        )
        assert meta['topic_type_hash'] == topics[name]['topic_metadata']['type_description_hash']
    records, indexed = rosbag2_records(run / 'run.mcap')
    assert 'rosbag2' in indexed and len(records) == 2
    assert all(list(r) == ['serialized_metadata'] for r in records)
    first, final = (yaml.safe_load(r['serialized_metadata']) for r in records)
    check_bag_metadata(first)
    assert (
        first['message_count'] == 0 and first['starting_time']['nanoseconds_since_epoch'] == NS_MAX
    )
    assert final == info

    # an independent reader, through metadata.yaml
    with Reader(run) as reader:
        assert reader.message_count == info['message_count']
        assert {c.topic: c.msgcount for c in reader.connections} == {
            n: e['message_count'] for n, e in topics.items()
        }
        got: dict[str, int] = {}
        for conn, _t, _raw in reader.messages():
            got[conn.topic] = got.get(conn.topic, 0) + 1
        assert got == {n: e['message_count'] for n, e in topics.items() if e['message_count']}
        for conn in reader.connections:
            recorded = topics[conn.topic]['topic_metadata']['offered_qos_profiles'][0]
            assert conn.ext.offered_qos_profiles[0].depth == recorded['depth']


def frame_bag(
    path: Path, n: int = 4, chunk_size: int = 1 << 20, close: bool = True
) -> bagio.BagWriter:
    """``n`` pattern frames (8 KiB each) written with BagWriter, 1 ns apart from t = 1 s."""
    writer = bagio.BagWriter(path, chunk_size=chunk_size)
    writer.add_topic(
        qos.FRAMES, qos.TOPIC_TYPES[qos.FRAMES], [qos.qos_dict(qos.topic_qos(qos.FRAMES))]
    )
    for i, f in enumerate(pattern_frames(num_phases=3)[:n]):
        writer.write(qos.FRAMES, serialize_message(conversions.frame_to_msg(f)), 1_000_000_000 + i)
    if close:
        writer.close()
    return writer


def test_runs_with_the_old_string_qos_still_read(tmp_path):
    """
    Check that runs recorded before the format fix still open with their recorded QoS.

    Runs recorded before the format fix (version 9 with offered_qos_profiles as a YAML string)
    still open in our readers and replay with their recorded QoS.
    """
    run = tmp_path / 'old'
    frame_bag(run / 'run.mcap')
    meta = yaml.safe_load((run / 'metadata.yaml').read_text())
    entry = meta['rosbag2_bagfile_information']['topics_with_message_count'][0]['topic_metadata']
    as_list = entry['offered_qos_profiles']
    entry['offered_qos_profiles'] = yaml.safe_dump(as_list, sort_keys=False)  # the old spelling
    (run / 'metadata.yaml').write_text(yaml.safe_dump(meta, sort_keys=False))

    info = bagio.read_bag_metadata(run)
    assert (
        info['topics_with_message_count'][0]['topic_metadata']['offered_qos_profiles'] == as_list
    )
    assert bagio.bag_topics(run)[qos.FRAMES]['count'] == 4
    assert len(list(bagio.read_bag(run))) == 4
    old, new = recorded_qos(entry['offered_qos_profiles']), recorded_qos(as_list)
    assert (
        old == new
        and new.depth == qos.STREAM_DEPTH
        and new.durability == qos.history_qos().durability
    )
    # rosbag2 before version 9 wrote the policies as rmw enum numbers
    humble = recorded_qos(
        '- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n  liveliness: 1\n'
    )
    assert humble == QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=5,
        reliability=ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def test_recover_writes_the_rosbag2_record_of_what_it_kept(tmp_path):
    path = tmp_path / 'killed' / 'run.mcap'
    # 16 KiB chunks close every 2 frames: frames 1-4 reach the disk, the 5th waits in memory
    writer = frame_bag(path, n=5, chunk_size=16 * 1024, close=False)
    writer.flush()
    damaged = tmp_path / 'damaged.mcap'
    damaged.write_bytes(
        path.read_bytes()
    )  # as a SIGKILL leaves it: no last chunk, summary, footer
    writer.close()
    result = bagio.recover(damaged, tmp_path / 'fixed.mcap')
    assert 0 < result['messages'] < 5
    records, indexed = rosbag2_records(tmp_path / 'fixed.mcap')
    assert 'rosbag2' in indexed and len(records) == 1
    info = yaml.safe_load(records[0]['serialized_metadata'])
    check_bag_metadata(info)
    assert info['message_count'] == result['messages'] and info['relative_file_paths'] == [
        'fixed.mcap'
    ]
    assert info['starting_time']['nanoseconds_since_epoch'] == 1_000_000_000
    assert info['custom_data'] == {'recorded_by': writer.metadata()['custom_data']['recorded_by']}


# ---------------------------------------------------------------------------- replay
T0 = 1_700_000_000_123_456_789  # recorded receive times: not on a whole second, 10 ms apart


def mixed_bag(path: Path) -> tuple[list[int], list[bytes]]:
    """
    Write a bag of frames and /diagnostics of a node that no longer runs, interleaved.

    Frames and /diagnostics of a node that no longer runs, interleaved; returns the frames'
    recorded times and the recorded diagnostics' bytes.
    """
    writer = bagio.BagWriter(path)
    writer.add_topic(
        qos.FRAMES, qos.TOPIC_TYPES[qos.FRAMES], [qos.qos_dict(qos.topic_qos(qos.FRAMES))]
    )
    writer.add_topic(
        qos.DIAGNOSTICS, qos.TOPIC_TYPES[qos.DIAGNOSTICS], [qos.qos_dict(qos.diagnostics_qos())]
    )
    frame_times, diags = [], []
    t = T0
    for i, f in enumerate(pattern_frames(num_phases=2)):
        writer.write(qos.FRAMES, serialize_message(conversions.frame_to_msg(f)), t)
        frame_times.append(t)
        t += 10_000_000
        if i % 2 == 0:
            arr = DiagnosticArray(
                status=[DiagnosticStatus(name='/recorded_node', message=f'old status {i}')]
            )
            diags.append(serialize_message(arr))
            writer.write(qos.DIAGNOSTICS, diags[-1], t)
            t += 10_000_000
    writer.close()
    return frame_times, diags


def graph_yaml_replay_params() -> dict:
    return yaml.safe_load((REPO / 'config' / 'graph.yaml').read_text())['/**/replay'][
        'ros__parameters'
    ]


def play(ros_context, executor, path, frames, wait_for, params: dict) -> Replay:
    """
    Start a Replay of ``path`` with ``params`` once the listeners are matched.

    Start a Replay of ``path`` with ``params``; the frames sink is created only once the /clock
    and /diagnostics listeners are matched with every publisher the replay has on those topics,
    so whatever it publishes there reaches them.
    """
    overrides = {**params, 'path': str(path), 'wait_for_subscribers': wait_for}
    replay = Replay(
        context=ros_context,
        parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
    )
    executor.add_node(replay)
    watched = [p for p in replay.publishers if p.topic_name in ('/clock', qos.DIAGNOSTICS)]
    assert spin_until(
        executor, lambda: all(p.get_subscription_count() >= 1 for p in watched), timeout=15
    )
    sink = rclpy.create_node('frames_sink', context=ros_context)
    sink.create_subscription(TaggedFrame, qos.FRAMES, frames.append, qos.stream_qos(), raw=True)
    executor.add_node(sink)
    assert spin_until(executor, lambda: replay.done, timeout=30)
    return replay


def test_replay_publishes_recorded_clock_and_keeps_recorded_diagnostics(
    ros_context, executor, tmp_path
):
    path = tmp_path / 'mixed.mcap'
    frame_times, recorded_diags = mixed_bag(path)
    clocks, diags, frames = [], [], []
    listener = rclpy.create_node('listener', context=ros_context)
    listener.create_subscription(
        Clock,
        '/clock',
        lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec),
        qos.stream_qos(),
    )
    listener.create_subscription(
        DiagnosticArray, qos.DIAGNOSTICS, diags.append, qos.diagnostics_qos(), raw=True
    )
    executor.add_node(listener)

    # the node's own defaults, /clock asked for
    replay = play(ros_context, executor, path, frames, 1, {'publish_clock': True})
    # /clock and the frames are two topics: the last clock may arrive after the last frame.
    assert spin_until(
        executor, lambda: len(frames) == len(frame_times) == 4 <= len(clocks), timeout=10
    )
    assert clocks == frame_times  # one per played message, its recorded time, in order
    assert qos.DIAGNOSTICS not in replay.pubs and replay.published == 4
    assert spin_until(executor, lambda: any(b'replay finished' in d for d in diags), timeout=10)
    assert not any(d in recorded_diags for d in diags), 'recorded /diagnostics were republished'
    assert not any(b'/recorded_node' in d for d in diags)
    for node in [n for n in executor.get_nodes() if n.get_name() in ('replay', 'frames_sink')]:
        executor.remove_node(node)
        node.destroy_node()

    # graph.yaml's replay section, recorded diagnostics asked for: they go out as recorded, and
    # no /clock (graph.yaml leaves publish_clock off)
    for log in (clocks, diags, frames):
        log.clear()
    config = graph_yaml_replay_params()
    assert config['publish_clock'] is False and config['republish_diagnostics'] is False
    replay = play(
        ros_context, executor, path, frames, 2, {**config, 'republish_diagnostics': True}
    )
    for key, value in config.items():
        if key not in ('wait_for_subscribers', 'republish_diagnostics'):
            assert replay.get_parameter(key).value == value, key
    assert replay.clock_pub is None and replay.published == 4 + len(recorded_diags)
    assert spin_until(
        executor, lambda: len(frames) == 4 and all(d in diags for d in recorded_diags), timeout=10
    )
    assert [d for d in diags if d in recorded_diags] == recorded_diags
    assert spin_until(executor, lambda: listener.count_publishers('/clock') == 0, timeout=5)
    assert clocks == []


# ---------------------------------------------------------------------------- package.xml
# Import name -> rosdep key. ROS packages: jazzy/distribution.yaml; python3-*: rosdep/python.yaml
# of github.com/ros/rosdistro (master, 8468e88); mlv_msgs: this workspace (msg_schemas/).
# None: rosdistro has no key; the README's Dependencies section gives its pip line.
IMPORT_KEYS = {
    'rclpy': 'rclpy',
    'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'builtin_interfaces',
    'std_msgs': 'std_msgs',
    'sensor_msgs': 'sensor_msgs',
    'diagnostic_msgs': 'diagnostic_msgs',
    'rosgraph_msgs': 'rosgraph_msgs',
    'mlv_msgs': 'mlv_msgs',
    'ament_index_python': 'ament_index_python',
    'launch': 'launch',
    'launch_ros': 'launch_ros',
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'cv2': 'python3-opencv',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'tqdm': 'python3-tqdm',
    'pydicom': None,
    'nibabel': None,
    'mcap': None,
    'foxglove': None,  # foxglove: PyPI foxglove-sdk
    'setuptools': 'python3-setuptools',
    'pytest': 'python3-pytest',
    'hypothesis': 'python3-hypothesis',
    'rosbags': 'python3-rosbags-pip',
    'catkin_pkg': 'python3-catkin-pkg-modules',
    'PIL': 'python3-pil',  # Pillow
    'meshio': 'python3-meshio',
    'websockets': 'python3-websockets',
    'google': 'python3-protobuf',  # test_live_view.py's Foxglove client
    'threadpoolctl': None,  # mlv_ros/threads.py; rosdistro has no key
    'gdcm': None,  # python-gdcm (tests only); Debian's python3-gdcm has no rosdep key
    'highdicom': None,  # tests only
    'ament_flake8': 'ament_flake8',
    'ament_pep257': 'ament_pep257',  # the lint tests
    # test_flake8 checks that flake8-docstrings' codes are among test_pep257's
    'flake8_docstrings': 'python3-flake8-docstrings',
    'pydocstyle': 'python3-pydocstyle',
    # DICOM decoders pydicom loads by itself; listed in case one is imported directly. No keys.
    'pylibjpeg': None,
    'libjpeg': None,
    'openjpeg': None,
    'rle': None,
    'jpeg_ls': None,
}
PIP_NAMES = {
    'pydicom': 'pydicom',
    'nibabel': 'nibabel',
    'mcap': 'mcap',
    'foxglove': 'foxglove-sdk',
    'threadpoolctl': 'threadpoolctl',
    'pylibjpeg': 'pylibjpeg',
    'libjpeg': 'pylibjpeg-libjpeg',
    'openjpeg': 'pylibjpeg-openjpeg',
    'rle': 'pylibjpeg-rle',
    'jpeg_ls': 'pyjpegls',
    'gdcm': 'python-gdcm',
    'highdicom': 'highdicom',
}
# Declared keys that no import names, and why.
NON_IMPORT_KEYS = {
    'python3-pytest-timeout': 'pytest.ini sets `timeout`',
    'python3-pytest-xdist': 'pytest.ini runs two workers (`-n 2`)',
    'ament_copyright': 'test_copyright.py takes it with pytest.importorskip (no wheel on PyPI)',
}


def top_level_imports(paths) -> set[str]:
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found.update(a.name.split('.')[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split('.')[0])
    local = (
        {'mlv_ros'}
        | {p.stem for p in (REPO / 'test').iterdir() if p.suffix == '.py' or p.is_dir()}
        | {p.stem for p in (REPO / 'bench').glob('*.py')}
    )  # tests compare against bench references
    return {
        m
        for m in found
        if m not in sys.stdlib_module_names and m not in local and m != '__future__'
    }


def test_package_xml_declares_every_import_with_a_rosdep_key():
    pkg = parse_package(str(REPO / 'package.xml'))  # the parser rosdep uses; raises on a bad file
    assert pkg.package_format == 3 and pkg.name == 'mlv_ros'
    assert [e.content for e in pkg.exports if e.tagname == 'build_type'] == ['ament_python']
    runtime = {d.name for d in pkg.exec_depends} | {d.name for d in pkg.build_export_depends}
    tests = {d.name for d in pkg.test_depends}
    build = {d.name for d in pkg.buildtool_depends} | {d.name for d in pkg.build_depends}

    installed = sorted((REPO / 'mlv_ros').rglob('*.py')) + sorted((REPO / 'launch').glob('*.py'))
    run_imports = top_level_imports(installed)
    test_imports = top_level_imports(sorted((REPO / 'test').rglob('*.py'))) - run_imports
    build_imports = top_level_imports([REPO / 'setup.py'])
    unmapped = sorted((run_imports | test_imports | build_imports) - set(IMPORT_KEYS))
    assert not unmapped, f'imports with no rosdep key (or None) in IMPORT_KEYS: {unmapped}'

    problems = []
    for imports, allowed, kind in (
        (run_imports, runtime, 'exec_depend'),
        (test_imports, tests | runtime, 'test_depend'),
        (build_imports, build, 'buildtool_depend'),
    ):
        for mod in sorted(imports):
            key = IMPORT_KEYS[mod]
            if key is not None and key not in allowed:
                problems.append(f'{mod}: <{kind}>{key}</{kind}> missing')
    declared = runtime | tests | build
    used = {IMPORT_KEYS[m] for m in run_imports | test_imports | build_imports} | set(
        NON_IMPORT_KEYS
    )
    problems += [f'{key} is declared but nothing imports it' for key in sorted(declared - used)]
    assert not problems, problems

    # what has no key is installed with pip, as the README says
    readme = (REPO / 'README.md').read_text()
    pip_lines = [line for line in readme.splitlines() if 'pip install' in line]
    for mod in sorted(run_imports | test_imports):
        if IMPORT_KEYS[mod] is None:
            assert any(
                re.search(rf'(?<![\w-]){re.escape(PIP_NAMES[mod])}(?![\w-])', line)
                for line in pip_lines
            ), f'README has no pip line for {PIP_NAMES[mod]} (import {mod}: no rosdep key)'

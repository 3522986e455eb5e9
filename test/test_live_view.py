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
The live view (``mlv-ros run --live``, ``mlv_ros/nodes/live_view.py``) seen by a Foxglove client.

The client is written here from the protocol, not from the server: ``websockets`` opens the
connection with the subprotocol foxglove-sdk 0.30 speaks (``foxglove.sdk.v1``, the successor of
``foxglove.websocket.v1``: same ops), reads the ``advertise`` op, sends ``subscribe``, and takes
the binary *message data* frames (opcode 0x01, uint32 subscription id, uint64 timestamp, payload,
little-endian). Protobuf payloads are decoded with the schema the server advertised (a
``FileDescriptorSet``, as Foxglove itself decodes them) by the ``protobuf`` package; JSON ones
as JSON. What arrives is compared with the run's recording (read with ``rosbags``).
"""

from __future__ import annotations

import asyncio
import base64
import json
import re
import socket
import struct
import subprocess
import threading
import time

from conftest import console_script
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mlv_ros import qos
from mlv_ros.runner import run_graph, RunStartError
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
import websockets

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

SUBPROTOCOL = 'foxglove.sdk.v1'
STUDY = {
    'source': 'phantom',
    'preset': 'normal',
    'snr': 20.0,
    'size': 128,
    'num_phases': 3,
    'order': 'phase_major',
}
OVERRIDES = {'registration': {'num_particles': 600}}
PACKED_TYPES = {
    1: 'u1',
    2: 'i1',
    3: '<u2',
    4: '<i2',
    5: '<u4',
    6: '<i4',
    7: '<f4',
    8: '<f8',
}  # PackedElementField


class FoxgloveClient:
    """
    Run a Foxglove WebSocket client in a thread, keeping every message of ``topics``.

    A Foxglove WebSocket client in a thread: subscribes to ``topics`` as they are advertised
    and keeps every message (channel topic → list of (log time ns, payload bytes)).
    """

    def __init__(self, url: str, topics: tuple[str, ...]):
        self.url, self.topics = url, set(topics)
        self.channels: dict[str, dict] = {}  # topic → advertised channel
        self.messages: dict[str, list] = {t: [] for t in topics}
        self.subscribed = threading.Event()  # every wanted topic that is advertised, subscribed
        self.error: BaseException | None = None
        self.server_info: dict | None = None
        self.statuses: list[dict] = []  # the server's status ops
        self.log: list[str] = []  # what happened, with times (shown when a check fails)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self._thread.start()

    async def _connect(self):
        deadline = time.monotonic() + 20
        while True:
            try:
                # max_queue None: the awaited pong below is read behind every queued frame; with
                # the default bound a burst of frames stopped the reading and the pong never came.
                return await websockets.connect(
                    self.url, subprotocols=[SUBPROTOCOL], max_size=None, max_queue=None
                )
            except OSError:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.05)

    async def _main(self):
        try:
            ws = await self._connect()
            assert ws.subprotocol == SUBPROTOCOL
            subs: dict[int, str] = {}
            async with ws:
                async for frame in ws:  # ends when the server closes (the run is over)
                    if isinstance(frame, str):
                        op = json.loads(frame)
                        if op['op'] == 'serverInfo':
                            self.server_info = op
                        elif op['op'] == 'status':
                            self.statuses.append(op)
                            await self._resubscribe(ws, op, subs)
                        elif op['op'] == 'advertise':
                            self._note(f'advertised {[c["topic"] for c in op["channels"]]}')
                            new = [c for c in op['channels'] if c['topic'] in self.topics]
                            for c in new:
                                self.channels[c['topic']] = c
                                subs[len(subs) + 1] = c['topic']
                            if new:
                                await ws.send(
                                    json.dumps(
                                        {
                                            'op': 'subscribe',
                                            'subscriptions': [
                                                {'id': sid, 'channelId': self.channels[t]['id']}
                                                for sid, t in subs.items()
                                                if t in {c['topic'] for c in new}
                                            ],
                                        }
                                    )
                                )
                                await (await ws.ping())  # the server has read the subscription
                                self._note(f'subscribed {[c["topic"] for c in new]}')
                            if all(
                                t in subs.values()
                                for t in self.topics & {qos.MOTION, '/lv/curves'}
                            ):
                                self.subscribed.set()
                        continue
                    opcode, sub_id, log_time = struct.unpack_from('<BIQ', frame)
                    if opcode == 0x01:
                        if not self.messages[subs[sub_id]]:
                            self._note(f'first message on {subs[sub_id]}')
                        self.messages[subs[sub_id]].append((log_time, bytes(frame[13:])))
        except websockets.ConnectionClosed:
            pass
        except BaseException as exc:  # reported by the test
            self.error = exc
            self.subscribed.set()

    async def _resubscribe(self, ws, status: dict, subs: dict[int, str]) -> None:
        # foxglove-sdk 0.30 can advertise a new channel before its server knows it for this client
        # (reproduced under load: 'Unknown channel ID: N', the subscription dropped); a client
        # that wants the channel asks again, as often as the server says so.
        found = re.fullmatch(r'Unknown channel ID: (\d+)', status.get('message', ''))
        if not found:
            return
        channel_id = int(found.group(1))
        self._note(f'server: {status["message"]}; subscribing again')
        await asyncio.sleep(0.05)
        await ws.send(
            json.dumps(
                {
                    'op': 'subscribe',
                    'subscriptions': [
                        {'id': sid, 'channelId': channel_id}
                        for sid, topic in subs.items()
                        if self.channels[topic]['id'] == channel_id
                    ],
                }
            )
        )

    def _note(self, what: str) -> None:
        self.log.append(f'{time.monotonic() - self._t0:.3f} s: {what}')

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)
        assert not self._thread.is_alive(), (
            f'the server did not close the connection when the run ended: {self.log}'
        )
        if self.error is not None:
            raise self.error

    def decode(self, topic: str) -> list:
        """Decode the messages of ``topic`` with the channel's advertised schema."""
        ch = self.channels[topic]
        if ch['encoding'] == 'json':
            return [json.loads(p) for _, p in self.messages[topic]]
        assert ch['encoding'] == ch['schemaEncoding'] == 'protobuf', ch
        files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch['schema']))
        pool = descriptor_pool.DescriptorPool()
        for f in files.file:
            pool.Add(f)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch['schemaName']))
        return [cls.FromString(p) for _, p in self.messages[topic]]


def cloud_array(msg) -> np.ndarray:
    """Return a decoded foxglove.PointCloud's points as a structured array (fields, stride)."""
    dtype = np.dtype(
        {
            'names': [f.name for f in msg.fields],
            'formats': [PACKED_TYPES[f.type] for f in msg.fields],
            'offsets': [f.offset for f in msg.fields],
            'itemsize': msg.point_stride,
        }
    )
    assert len(msg.data) % msg.point_stride == 0
    return np.frombuffer(msg.data, dtype=dtype)


def recorded(mcap) -> dict:
    """
    Return per phase of the recording its cloud, stamp, verdict and metrics' volume.

    Per phase of the recording: its cloud (structured, from the PointCloud2 bytes), stamp,
    verdict and metrics' volume.
    """
    store = get_typestore(Stores.ROS2_JAZZY)
    clouds, states, volumes = {}, {}, {}
    with AnyReader([mcap], default_typestore=store) as reader:
        conns = [
            c for c in reader.connections if c.topic in (qos.MOTION, qos.MODEL_STATE, qos.METRICS)
        ]
        for conn, _t, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            key = (m.header.stamp.sec, m.header.stamp.nanosec)
            if conn.topic == qos.MOTION:
                fmt = {7: '<f4', 8: '<f8'}
                dtype = np.dtype(
                    {
                        'names': [f.name for f in m.fields],
                        'formats': [fmt[f.datatype] for f in m.fields],
                        'offsets': [f.offset for f in m.fields],
                        'itemsize': m.point_step,
                    }
                )
                clouds[key] = (np.frombuffer(m.data.tobytes(), dtype=dtype), m.header.frame_id)
            elif conn.topic == qos.MODEL_STATE:
                states[key] = (m.phase_index, m.verdict)
            else:
                volumes[m.phase_index] = (m.verdict, m.cavity_volume_ml, m.time_fraction)
    return {
        'phases': {states[k][0]: (k, states[k][1], *clouds[k]) for k in clouds if k in states},
        'metrics': volumes,
    }


def recorded_slice(mcap, view: int, slice_index: int) -> tuple[dict, dict]:
    """
    Return one slice of the recording: its frames' shapes and its tag points by stamp.

    One slice of the recording: {stamp: (rows, columns)} of its frames and {stamp: pixel_rc}
    of its tag points (rclpy reads TagPoints: rosbags refuses an empty set's alignment bytes).
    """
    from mlv_msgs.msg import TaggedFrame, TagPoints
    from mlv_ros import bagio
    from rclpy.serialization import deserialize_message

    frames, tags = {}, {}
    for m in bagio.read_bag(mcap, topics=[qos.FRAMES, qos.TAG_POINTS]):
        msg = deserialize_message(m.data, TaggedFrame if m.topic == qos.FRAMES else TagPoints)
        if (msg.view, msg.slice_index) != (view, slice_index):
            continue
        key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
        if m.topic == qos.FRAMES:
            frames[key] = (msg.image.height, msg.image.width)
        else:
            tags[key] = np.array(msg.pixel_rc, dtype=np.float64).reshape(-1, 2)
    return frames, tags


def test_a_foxglove_client_receives_the_cloud_of_every_phase(tmp_path):
    clients = []

    def progress(line: str):
        # The run's live view line comes after every node is up and before the input flows:
        # connect and subscribe there, so nothing is published before the client listens.
        if 'live view: ws://' in line:
            url = line.split('live view: ')[1].split()[0]
            clients.append(
                FoxgloveClient(
                    url, (qos.MOTION, '/lv/curves', '/mlv/sa_00/image', '/mlv/sa_00/tags')
                )
            )
            assert clients[0].subscribed.wait(30), (
                'the client did not get to subscribe within 30 s'
            )

    summary = run_graph(
        STUDY,
        tmp_path / 'run',
        overrides=OVERRIDES,
        timeout=300,
        progress=progress,
        live={'port': 0},
    )
    assert clients, "no live view line in the run's progress"
    client = clients[0]
    client.join(30)
    assert summary['phases_complete'], summary
    assert client.server_info['name'] == 'mlv_ros live view'
    assert client.channels[qos.MOTION]['schemaName'] == 'foxglove.PointCloud'
    assert client.channels['/lv/curves']['encoding'] == 'json'

    rec = recorded(tmp_path / 'run' / 'run.mcap')
    shown = {p for p, (_k, verdict, *_) in rec['phases'].items() if verdict != 2}
    assert sorted(rec['phases']) == list(range(STUDY['num_phases']))
    assert shown, 'every phase failed: nothing to compare'
    live = {}
    for msg in client.decode(qos.MOTION):
        live[(msg.timestamp.seconds, msg.timestamp.nanos)] = msg
    # One cloud per phase that is a measurement (failed ones are never drawn), and only those.
    assert summary['live_view']['phases_shown'] == len(shown) == len(live)
    assert sorted(int(p) for p in summary['live_view']['phases_not_shown']) == sorted(
        set(rec['phases']) - shown
    )
    for phase in shown:
        key, _verdict, points, frame_id = rec['phases'][phase]
        assert key in live, f'phase {phase} (stamp {key}) not received'
        msg = live[key]
        got = cloud_array(msg)
        assert msg.frame_id == frame_id == 'patient'
        assert (msg.pose.orientation.w, msg.pose.position.x) == (1.0, 0.0)
        assert got.shape == points.shape == (OVERRIDES['registration']['num_particles'],)
        assert (
            got.dtype.names
            == points.dtype.names
            == ('x', 'y', 'z', 'dx', 'dy', 'dz', 'err', 'ecc', 'ell')
        )
        for field in ('x', 'ecc'):  # the very float32 values recorded
            np.testing.assert_array_equal(got[field], points[field])
    # The curves: one object per phase, the recorded volume (not for a failed phase).
    curves = {c['phase_index']: c for c in client.decode('/lv/curves')}
    assert sorted(curves) == sorted(rec['metrics'])
    for phase, (verdict, volume, fraction) in rec['metrics'].items():
        assert curves[phase]['verdict'] == verdict and curves[phase][
            'time_fraction'
        ] == pytest.approx(fraction)
        if verdict == 2:
            assert 'cavity_volume_ml' not in curves[phase]
        else:
            assert curves[phase]['cavity_volume_ml'] == pytest.approx(volume, rel=1e-12)
    # The most basal SA slice: its image of every phase (served with that phase), and its tag
    # points where the recording has them (Foxglove counts from the corner of the first pixel:
    # +0.5), paired with their image by the frame's stamp.
    frames, tags = recorded_slice(tmp_path / 'run' / 'run.mcap', view=0, slice_index=0)
    images = {
        (m.timestamp.seconds, m.timestamp.nanos): m for m in client.decode('/mlv/sa_00/image')
    }
    assert sorted(images) == sorted(frames) and len(frames) == STUDY['num_phases'], client.log
    for key, (rows, cols) in frames.items():
        m = images[key]
        assert (m.encoding, m.height, m.width, m.step, len(m.data)) == (
            'mono8',
            rows,
            cols,
            cols,
            rows * cols,
        )
        assert (
            np.ptp(np.frombuffer(m.data, np.uint8)) > 100
        )  # windowed to show the tags, not a flat field
    annotations = {
        (m.timestamp.seconds, m.timestamp.nanos): m for m in client.decode('/mlv/sa_00/tags')
    }
    assert (
        sorted(annotations) == sorted(tags) == sorted(frames)
    )  # one set per image, with its stamp
    for key, rc in tags.items():
        (drawn,) = annotations[key].points
        got = np.array([(p.x, p.y) for p in drawn.points]).reshape(-1, 2)
        np.testing.assert_allclose(got, rc[:, ::-1] + 0.5, atol=1e-9)


def free_port() -> socket.socket:
    """Return a listening socket on a free loopback port (held while it lives)."""
    s = socket.socket()
    s.bind(('127.0.0.1', 0))
    s.listen()
    return s


def test_live_port_in_use_is_one_line_and_leaves_nothing(tmp_path):
    with free_port() as taken:
        port = taken.getsockname()[1]
        with pytest.raises(
            RunStartError, match=f'port {port} on 127.0.0.1 is in use.*--live-port N'
        ):
            run_graph(
                STUDY,
                tmp_path / 'api',
                overrides=OVERRIDES,
                progress=lambda *_: None,
                live={'port': port},
            )
        assert not (tmp_path / 'api').exists()
        proc = subprocess.run(
            [
                console_script('mlv-ros'),
                'run',
                '--phantom',
                'normal',
                '--live-port',
                str(port),
                '--out',
                str(tmp_path / 'cli'),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'in use' in lines[0] and '--live-port N' in lines[0], proc.stderr
    assert 'Traceback' not in proc.stderr and not (tmp_path / 'cli').exists()


def test_a_failed_phase_is_not_drawn_and_foxglove_is_told_why(ros_context, executor):
    """
    Check that a failed phase's cloud never reaches the 3D panel and Foxglove gets a status.

    A phase whose verdict is failed is no measurement: its cloud never reaches the 3D panel;
    Foxglove gets a status naming the phase and why (degraded phases are drawn and listed).
    """
    from graphkit import Probe
    from mlv_ros import conversions
    from mlv_ros.core.types import ModelState
    from mlv_ros.nodes.live_view import LiveView
    from rclpy.parameter import Parameter

    view = LiveView(context=ros_context, parameter_overrides=[Parameter('port', value=0)])
    probe = Probe(ros_context)
    for node in (view, probe):
        executor.add_node(node)
    client = FoxgloveClient(view.url, (qos.MOTION, '/lv/curves'))
    assert client.subscribed.wait(30), client.log
    rng = np.random.default_rng(3)
    verdicts = {0: (0, ''), 1: (2, 'no SA slice with 3+ tag points'), 2: (1, 'few tag points')}
    for phase, (level, why) in verdicts.items():
        cols = {
            k: rng.normal(size=50) for k in ('x', 'y', 'z', 'dx', 'dy', 'dz', 'err', 'ecc', 'ell')
        }
        stamp = 10.0 + phase
        probe.publish(
            qos.MOTION,
            conversions.cloud_to_msg(conversions.structured(cols), conversions.make_header(stamp)),
        )
        probe.publish(
            qos.MODEL_STATE,
            conversions.model_state_to_msg(
                ModelState(
                    phase_index=phase,
                    num_phases=3,
                    verdict=level,
                    verdict_reasons=why,
                    num_particles=50,
                ),
                stamp,
            ),
        )
    from conftest import spin_until

    assert spin_until(executor, lambda: len(view.phases_served) == 3, 30), view.phases_served
    assert (
        view.phases_not_shown == {1: 'no SA slice with 3+ tag points'} and view.clouds_served == 2
    )
    assert spin_until(
        executor, lambda: len(client.messages[qos.MOTION]) == 2 and len(client.statuses) == 2, 10
    ), client.log
    # A client that subscribes late gets the latest phase shown at once, then what follows.
    late = FoxgloveClient(view.url, (qos.MOTION,))
    assert late.subscribed.wait(30), late.log
    assert spin_until(executor, lambda: len(late.messages[qos.MOTION]) == 1, 10), late.log
    executor.remove_node(view)
    view.destroy_node()  # stops the server: the clients' connections end
    client.join(10)
    late.join(10)
    assert [(m.timestamp.seconds, m.timestamp.nanos) for m in late.decode(qos.MOTION)] == [(12, 0)]
    assert len(client.messages[qos.MOTION]) == 3  # the first client sees the latest cloud again
    stamps = [(m.timestamp.seconds, m.timestamp.nanos) for m in client.decode(qos.MOTION)]
    assert stamps == [(10, 0), (12, 0), (12, 0)]
    said = {s['message']: s['level'] for s in client.statuses}
    assert said == {
        'phase 1 failed, not shown: no SA slice with 3+ tag points': 2,
        'phase 2 degraded (use with care): few tag points': 1,
    }


def test_layout_shows_what_the_live_view_serves():
    """
    Check that config/foxglove_layout.json names the live view's channels and fields.

    config/foxglove_layout.json (Foxglove's layout file: configById + a mosaic of panel ids)
    names the live view's channels and fields, and every panel it places has a config.
    """
    from conftest import REPO
    from mlv_ros.conversions import curves_schema
    from mlv_ros.nodes.live_view import CLOUD_CHANNEL, CURVES_CHANNEL
    from mlv_ros.conversions import MOTION_FIELDS

    layout = json.loads((REPO / 'config' / 'foxglove_layout.json').read_text())

    def panels(node):
        return [node] if isinstance(node, str) else panels(node['first']) + panels(node['second'])

    placed = panels(layout['layout'])
    assert sorted(placed) == sorted(layout['configById'])
    kinds = sorted(p.split('!')[0] for p in placed)
    assert kinds == ['3D', 'Image', 'Image', 'Plot', 'Plot']
    fields = set(curves_schema()['properties'])
    for pid, cfg in layout['configById'].items():
        if pid.startswith('3D!'):
            ((topic, settings),) = cfg['topics'].items()
            assert topic == '/' + CLOUD_CHANNEL and settings['colorField'] in MOTION_FIELDS
            assert settings['minValue'] < 0 < settings['maxValue'] and cfg['followTf'] == 'patient'
        elif pid.startswith('Image!'):
            mode = cfg['imageMode']
            assert re.fullmatch(r'/mlv/(sa|la)_\d\d/image', mode['imageTopic'])
            assert list(mode['annotations']) == [mode['imageTopic'].replace('/image', '/tags')]
        else:
            paths = [p['value'] for p in cfg['paths']] + [cfg['xAxisPath']['value']]
            assert all(
                p.startswith(f'/{CURVES_CHANNEL}.') and p.split('.', 1)[1] in fields for p in paths
            ), paths


def test_channels_follow_the_nodes_namespace(ros_context):
    from mlv_ros.nodes.live_view import LiveView
    from rclpy.parameter import Parameter

    view = LiveView(
        context=ros_context, namespace='/study2', parameter_overrides=[Parameter('port', value=0)]
    )
    try:
        assert view.cloud_channel.topic() == '/study2/lv/motion'
        assert view.curves_channel.topic() == '/study2/lv/curves'
        assert view._slice(0, 3)['image'].topic() == '/study2/mlv/sa_03/image'
        assert view._slice(1, 0)['tags'].topic() == '/study2/mlv/la_00/tags'
        assert view.topic_name(qos.MOTION) == '/study2/lv/motion'  # the ROS topic it reads
    finally:
        view.destroy_node()

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
live_view: the run, live in Foxglove — a ``foxglove_bridge``-style node on foxglove-sdk.

It subscribes to the graph's results and serves them over a Foxglove WebSocket (``host``:``port``,
default ``ws://127.0.0.1:8765``; Foxglove → Open connection → Foxglove WebSocket), in Foxglove's
own schemas, so its panels draw them without any message definition of ours:

- ``/lv/motion`` (``foxglove.PointCloud``): the LV particles of each phase, as the solver
  publishes them (``x y z`` mm in frame ``patient``, DICOM LPS, as in the recording; ``dx dy dz``
  displacement from ED, mm; ``err ecc ell`` Green–Lagrange strain). The 3D panel colours them by
  a strain field; phase after phase the heart beats. A phase whose verdict is *failed* is not a
  measurement and is not shown: Foxglove's problems list says so (degraded phases are shown and
  listed).
- ``/mlv/<sa|la>_<NN>/image`` (``foxglove.RawImage``, mono8) and ``/mlv/<sa|la>_<NN>/tags``
  (``foxglove.ImageAnnotations``): each slice's tagged image and its tracked tag points, paired
  by their frame's stamp (the Image panel syncs them), served with the phase they belong to: when
  a phase's cloud is served (failed or not: they are the input), every slice's image of that
  phase follows, so images and model move together (frames stream in long before their phase is
  solved). Grey levels are windowed per slice from its first frame (1st–99.5th percentile), so
  the tags' fading stays visible.
- ``/lv/curves`` (JSON, :func:`mlv_ros.conversions.curves_schema`): one object per analysed
  phase — time fraction, cavity volume, ejection fraction, apical and basal twist, torsion,
  verdict — for the Plot panel (x: ``/lv/curves.time_fraction``); the curves grow as phases come.

Under a namespace every channel name starts with it (``/study2/lv/motion``). Channels are served
as phases are solved. A client that subscribes late gets, at once, the latest cloud and every
phase shown so far of the slices it subscribes to (a few tenths of a second later: the executor
serves them), then the phases from then on (the recording holds them all).
``config/foxglove_layout.json`` arranges the panels. Run isolation as every node: the first study
taken is kept, model states of another are reported and their clouds dropped.

Parameters (``config/graph.yaml``): ``host``, ``port`` (0 = any free port), ``images``,
``catch_up``, ``max_unpaired``, ``message_backlog``. A port that cannot be bound (in use) stops
the node at start with one line saying so (exit 2).
"""

from __future__ import annotations

import json

from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import MotionMetrics, TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.streaming import StampPairer
from mlv_ros.core.verdict import DEGRADED, FAILED, Verdict
from mlv_ros.nodes.common import GraphNode, OK, run_node, stamp_key, WARN
from mlv_ros.settings import PAIRING
from sensor_msgs.msg import PointCloud2

CLOUD_CHANNEL = 'lv/motion'  # foxglove.PointCloud, relative to the node's namespace
CURVES_CHANNEL = 'lv/curves'  # JSON (conversions.curves_schema)
SLICE_CHANNEL = (
    'mlv/{name}/{kind}'  # kind: image (foxglove.RawImage) | tags (foxglove.ImageAnnotations)
)


def slice_name(view: int, slice_index: int) -> str:
    """``sa_02`` / ``la_00``: the slice's part of its channel names."""
    return f'{"la" if view == TaggedFrame.VIEW_LA else "sa"}_{slice_index:02d}'


def port_error(host: str, port: int, exc: Exception) -> str:
    """One line for a server that could not listen, with the fix."""
    text = str(exc)
    if 'in use' in text or 'os error 98' in text:
        return (
            f'live view: port {port} on {host} is in use (another live view or Foxglove bridge?); '
            f'choose a free one (port:=N; mlv-ros run --live-port N)'
        )
    return (
        f'live view: cannot listen on {host}:{port}: '
        f'{text.removeprefix("FoxgloveError: ")}; check host and port'
    )


class _Subscriptions:
    """
    foxglove ServerListener noting what had been served when each subscription came.

    ``state()``: clouds served, phases served; called from the server's thread. The node serves
    what the subscriber missed from its own (:meth:`LiveView._serve_subscribed`).
    """

    def __init__(self, state):
        self.state = state
        self.topics: list[tuple] = []  # (topic, clouds served, phases served) at subscription
        self.count = 0

    def on_subscribe(self, client, channel) -> None:
        self.topics.append((channel.topic, *self.state()))
        self.count += 1

    def on_unsubscribe(self, client, channel) -> None:
        self.count -= 1


class LiveView(GraphNode):
    DIAGNOSTIC_TASK = 'live view'

    def __init__(self, **node_kwargs):
        super().__init__('live_view', **node_kwargs)
        try:
            import foxglove
            from foxglove.channels import PointCloudChannel
        except ImportError as exc:  # a ROS install without the pip-only SDK
            raise ValueError(
                f"the live view needs Foxglove's SDK ({exc}): pip install foxglove-sdk==0.30.3"
            ) from None

        port, catch_up, backlog = self._declare_parameters()
        self._fox = foxglove
        self.fox_context = foxglove.Context()
        prefix = self.get_namespace().rstrip('/')
        self._channel_name = lambda rel: f'{prefix}/{rel}'
        self.clouds_served = 0
        self._served = (
            frozenset()
        )  # phases served, replaced (not changed) as phases go out: read by the listener
        self._fox_listener = _Subscriptions(lambda: (self.clouds_served, self._served))
        self._start_server(port, backlog)
        self.cloud_channel = PointCloudChannel(
            self._channel_name(CLOUD_CHANNEL), context=self.fox_context
        )
        self.curves_channel = foxglove.Channel(
            self._channel_name(CURVES_CHANNEL),
            context=self.fox_context,
            schema=foxglove.Schema(
                name='mlv_ros.PhaseCurves',
                encoding='jsonschema',
                data=json.dumps(conversions.curves_schema()).encode(),
            ),
            message_encoding='json',
        )
        # (view, slice) → {"image": channel, "tags": channel, "window": (lo, hi), "images": {phase:
        # RawImage}, "tags_by_phase": {phase: ImageAnnotations}}
        self._slices: dict = {}
        self.phases_served: set[int] = set()  # phases whose cloud (or verdict) went out
        self._last_cloud = (
            None  # the latest foxglove.PointCloud served (for a client that subscribes late)
        )
        # stamp → (points, header) of a cloud / model state, each waiting for the other
        self._pairer = StampPairer(self.max_unpaired)
        self.held_clouds.append((qos.MOTION, self._pairer))
        self.phases_not_shown: dict[int, str] = {}  # failed phase → reasons
        self.curves_served = 0
        self.messages_handled = 0
        self.subscribe(qos.MOTION, PointCloud2, self._on_motion)
        self.subscribe(qos.MODEL_STATE, ModelStateMsg, self._on_state)
        self.subscribe(qos.METRICS, MotionMetrics, self._on_metrics)
        if self.images:
            self.subscribe(qos.FRAMES, TaggedFrame, self._on_frame, catch_up=catch_up)
            self.subscribe(qos.TAG_POINTS, TagPoints, self._on_tags, catch_up=catch_up)
        self.create_timer(0.2, self._serve_subscribed)
        self.report(OK, 'serving', url=self.url)

    def _start_server(self, port: int, backlog: int) -> None:
        """Start the Foxglove WebSocket server (``port`` 0: any free one); say why it cannot."""
        try:
            self.server = self._fox.start_server(
                name='mlv_ros live view',
                host=self.host,
                port=port,
                context=self.fox_context,
                message_backlog_size=backlog,
                server_listener=self._fox_listener,
            )
        except RuntimeError as exc:
            raise ValueError(port_error(self.host, port, exc)) from None
        self.port = self.server.port
        self.url = f'ws://{self.host}:{self.port}'

    def _declare_parameters(self):
        """
        Declare the node's parameters: where it serves, what, and how much it holds back.

        Returns the ones used only while starting: ``port``, ``catch_up`` and ``backlog``.
        """
        self.host = self.param(
            'host',
            '127.0.0.1',
            'address the Foxglove WebSocket listens on '
            '(127.0.0.1: this machine only; 0.0.0.0: every interface)',
        )
        port = self.param(
            'port',
            8765,
            'Foxglove WebSocket port (0 = any free port)',
            min_value=0,
            max_value=65535,
        )
        self.images = self.param('images', True, "serve each slice's images and tag points")
        catch_up = self.param(
            'catch_up',
            True,
            'take frames and tag points with their history (TRANSIENT_LOCAL); '
            'false for a publisher without history',
        )
        self.declare_settings(PAIRING)  # self.max_unpaired
        backlog = self.param(
            'message_backlog',
            1024,
            'messages queued per Foxglove client (the oldest go when a slow client falls behind)',
            min_value=16,
            max_value=1000000,
        )
        return port, catch_up, backlog

    def _serve_subscribed(self) -> None:
        """
        Serve what a client that just subscribed missed.

        The latest cloud, unless a newer one went out since it subscribed; a slice's images and tag
        points of the phases shown before it subscribed (others subscribed then see them again,
        with the same stamps).
        """
        topics = self._fox_listener.topics
        while topics:
            topic, clouds_then, served_then = topics.pop(0)
            if (
                topic == self.cloud_channel.topic()
                and clouds_then
                and clouds_then == self.clouds_served
            ):
                self.cloud_channel.log(self._last_cloud)
            for ch in list(self._slices.values()):
                for kind, held in (('image', ch['images']), ('tags', ch['tags_by_phase'])):
                    if ch[kind].topic() == topic:
                        for phase in sorted(served_then & set(held)):
                            ch[kind].log(held[phase])

    # ------------------------------------------------------------------ motion clouds
    def _on_motion(self, msg: PointCloud2) -> None:
        self.messages_handled += 1
        if self.other_study_cloud(qos.MOTION, msg):
            return
        points = self.converted(msg, _finite_cloud, 'bad motion cloud not shown')
        if points is None:
            return
        key = stamp_key(msg.header.stamp)
        item = (points, msg.header)
        self.hold(self._pairer, 'cloud', key, item, self._serve, 'unpaired motion cloud not shown')

    def _on_state(self, msg: ModelStateMsg) -> None:
        self.messages_handled += 1
        if self.other_study_state(msg, qos.MODEL_STATE, phase=msg.phase_index):
            return
        state = self.converted(
            msg,
            conversions.msg_to_model_state,
            'bad model state: its phase is not shown',
            phase=msg.phase_index,
        )
        if state is None:
            return
        self.study.adopt(state.study_id, state.run_id)
        key = stamp_key(msg.header.stamp)
        self.hold(self._pairer, 'state', key, state, self._serve, 'unpaired model state not shown')

    def _serve(self) -> None:
        """Serve every phase whose cloud and state (same stamp) are both in."""
        for _, (points, header), state in self._pairer.pairs():
            self._serve_phase(points, header, state)

    def _serve_phase(self, points, header, state) -> None:
        from foxglove import StatusLevel

        phase = int(state.phase_index)
        verdict = Verdict.from_parts(state.verdict, state.verdict_reasons)
        self.phases_served.add(phase)
        self._served = frozenset(self.phases_served)
        for ch in self._slices.values():  # the images of this phase, with their tag points
            for kind, held in (('image', ch['images']), ('tags', ch['tags_by_phase'])):
                if phase in held:
                    ch[kind].log(held[phase])
        if verdict.level >= FAILED:
            # Not a measurement: never drawn. Foxglove's problems list says why.
            self.phases_not_shown[phase] = verdict.text
            self.server.publish_status(
                f'phase {phase} failed, not shown: {verdict.text}',
                StatusLevel.Error,
                id=f'phase {phase}',
            )
            return
        if verdict.level == DEGRADED:
            self.server.publish_status(
                f'phase {phase} degraded (use with care): {verdict.text}',
                StatusLevel.Warning,
                id=f'phase {phase}',
            )
        self._last_cloud = conversions.cloud_to_foxglove(
            points, header.stamp, header.frame_id or conversions.PATIENT_FRAME
        )
        self.cloud_channel.log(self._last_cloud)
        self.clouds_served += 1
        self.report(
            OK,
            'serving',
            url=self.url,
            phases_shown=self.clouds_served,
            phases_not_shown=len(self.phases_not_shown),
            client_subscriptions=self._fox_listener.count,
        )

    # ------------------------------------------------------------------ curves
    def _on_metrics(self, msg: MotionMetrics) -> None:
        self.messages_handled += 1
        if self.foreign(
            msg.study_id,
            qos.METRICS,
            run_id=msg.run_id,
            phase=msg.phase_index,
            stamp=conversions.stamp_text(msg.header.stamp),
        ):
            return
        curves = self.converted(msg, _curves, 'bad metrics not shown')
        if curves is None:
            return
        self.curves_channel.log(curves)
        self.curves_served += 1

    # ------------------------------------------------------------------ images and tag points
    def _slice(self, view: int, slice_index: int) -> dict:
        key = (int(view), int(slice_index))
        if key not in self._slices:
            from foxglove.channels import ImageAnnotationsChannel, RawImageChannel

            name = slice_name(*key)
            self._slices[key] = {
                'image': RawImageChannel(
                    self._channel_name(SLICE_CHANNEL.format(name=name, kind='image')),
                    context=self.fox_context,
                ),
                'tags': ImageAnnotationsChannel(
                    self._channel_name(SLICE_CHANNEL.format(name=name, kind='tags')),
                    context=self.fox_context,
                ),
                'window': None,
                'images': {},
                'tags_by_phase': {},
            }
        return self._slices[key]

    def _on_frame(self, msg: TaggedFrame) -> None:
        self.messages_handled += 1
        stamp = conversions.stamp_text(msg.header.stamp)
        if self.foreign(msg.study_id, qos.FRAMES, run_id=msg.run_id, stamp=stamp):
            return
        try:
            frame = conversions.msg_to_frame(msg, allow_nonfinite=True)
            ch = self._slice(frame.view, frame.slice_index)
            ch['window'] = ch['window'] or conversions.display_window(frame.image)
            image = conversions.image_to_foxglove(
                frame.image,
                ch['window'],
                msg.header.stamp,
                msg.header.frame_id or conversions.PATIENT_FRAME,
            )
        except ValueError as exc:
            self.report(WARN, 'frame not shown', stamp=stamp, reason=str(exc))
            return
        ch['images'][frame.phase_index] = image
        if frame.phase_index in self.phases_served:  # a late frame of a phase already shown
            ch['image'].log(image)

    def _on_tags(self, msg: TagPoints) -> None:
        self.messages_handled += 1
        stamp = conversions.stamp_text(msg.header.stamp)
        if self.foreign(msg.study_id, qos.TAG_POINTS, run_id=msg.run_id, stamp=stamp):
            return
        try:
            points = conversions.msg_to_tagpoints(msg)
            ann = conversions.tagpoints_to_foxglove(points.pixel_rc, msg.header.stamp)
        except ValueError as exc:
            self.report(WARN, 'tag points not shown', stamp=stamp, reason=str(exc))
            return
        ch = self._slice(points.view, points.slice_index)
        ch['tags_by_phase'][points.phase_index] = ann
        if points.phase_index in self.phases_served:
            ch['tags'].log(ann)

    def destroy_node(self):
        server = getattr(self, 'server', None)
        if server is not None:
            server.stop()
            self.server = None
        return super().destroy_node()


def _finite_cloud(msg: PointCloud2):
    """Return a motion cloud's points, refusing non-finite positions (ValueError)."""
    return conversions.msg_to_cloud(msg, finite=('x', 'y', 'z'))


def _curves(msg: MotionMetrics) -> dict:
    """Return a metrics message as the curves served (ValueError: unusable metrics)."""
    return conversions.metrics_to_curves(conversions.msg_to_metrics(msg))


def main(args=None):
    return run_node(LiveView, args)


if __name__ == '__main__':
    raise SystemExit(main())

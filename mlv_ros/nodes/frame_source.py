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
frame_source: publishes tagged cine frames (``mlv_msgs/TaggedFrame`` on /mlv/frames).

The frames come from a simulator preset, a DICOM directory, a recorded bag, or the built-in test
pattern.

Order is slice-major (as scanners acquire: each slice's whole cine in one breath-hold) or
phase-major; rate is real time × ``rate_factor``, or as fast as possible (``rate_factor: 0``),
which RELIABLE QoS with a deep queue absorbs without loss. Paced, one frame goes out per timer
tick when due; as fast as possible, :data:`BURST_FRAMES` (half the topic's depth) go out in one
tick, and a burst waits until every subscriber has acknowledged the previous one, so no frame is
ever pushed out of the writer's history unacknowledged.

A phantom is simulated as it is published (the frames' plan when the node starts, each image
when it is due, see :class:`~mlv_ros.core.sim.study.StudyRenderer`), in a process of its own
(:mod:`mlv_ros.render_process`) where the run may use several (two cores or more, no
``MLV_ROS_ONE_PROCESS``), else in the node between its other work, while it waits for
subscribers too; so the first frames go out while the rest are simulated, with the very images
of the whole study simulated at once. Published images are not kept by the node.

A DICOM directory loads its tagged study (the one with the most tagged cines, or the
StudyInstanceUID in ``study``); each skipped file, each series not used (and each cine missing
phases) gets its own /diagnostics entry naming it, published before the frames, one per timer
tick, once a /diagnostics listener is there (up to ``wait_timeout_s``); so does the choice of
study when the folder holds several or some of the study was left out (``input_complete``,
``left_out``, ``dicom_choice`` keep it for the caller).

Every frame carries the study it belongs to (``study_id``, see :func:`study_id_for`): the DICOM
StudyInstanceUID (a hash of the images without one), a hash of the simulation parameters and
seed, or what a recording's frames carry (a hash of the bag's path for frames recorded before
the field existed), and the run it belongs to (``run_id``: a nonce drawn when the node starts,
frames of a recording taking this run's). Downstream nodes keep to that study and run and ignore
any other on the domain, a second run of the same study included.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
import secrets
import time

from mlv_msgs.msg import TaggedFrame
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.types import Frame
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, SubscriberWait, WARN
from rclpy._rclpy_pybind11 import InvalidHandle
from rclpy.duration import Duration

SOURCES = ('phantom', 'dicom', 'bag', 'pattern')
ORDERS = ('slice_major', 'phase_major')
# Most frames published in one timer tick. The source shares its executor with the run's other
# nodes (registration, solver, recorder), whose callbacks held a one-frame-per-tick source back by
# seconds. Half the topic's depth: a burst starts only once the previous one is acknowledged, so
# the KEEP_LAST writer history never holds more than this unacknowledged, and a subscriber's queue
# (as deep) holds two whole bursts it has not taken yet; the default study (275 frames) goes out
# in one tick, and the other nodes get the executor at least every 500 frames (~1-2 s).
BURST_FRAMES = qos.STREAM_DEPTH // 2
ACK_POLL_NS = 10_000_000  # once every frame is out: how often to look whether all are acknowledged


def order_frames(frames: list[Frame], order: str) -> list[Frame]:
    """Sort frames slice-major (view, slice, phase) or phase-major (phase, view, slice)."""
    if order == 'slice_major':
        return sorted(frames, key=lambda f: (f.view, f.slice_index, f.phase_index))
    return sorted(frames, key=lambda f: (f.phase_index, f.view, f.slice_index))


def read_bag_frames(path) -> list[Frame]:
    """
    Read every ``/mlv/frames`` message of a recording as Frames.

    Whatever namespace it was recorded in, also from recordings made before fields were appended to
    TaggedFrame (their ``study_id`` is empty).
    """
    return [
        conversions.msg_to_frame(bagio.deserialize(m.data, TaggedFrame, m.missing))
        for m in bagio.read_bag(path, topics=[qos.FRAMES], any_namespace=True)
    ]


def _digest(*parts) -> str:
    h = hashlib.blake2b(digest_size=10)
    for part in parts:
        h.update(part if isinstance(part, (bytes, bytearray, memoryview)) else str(part).encode())
        h.update(b'\0')
    return h.hexdigest()


def images_digest(frames: list[Frame]) -> str:
    """Hash a study's images: indices, geometry and pixels of every frame, in a fixed order."""
    parts = []
    for f in sorted(frames, key=lambda f: (f.view, f.slice_index, f.phase_index)):
        g = f.geometry
        parts += [
            f'{f.view} {f.slice_index} {f.phase_index} {f.num_phases} {f.series_uid}',
            g.image_position.tobytes(),
            g.row_direction.tobytes(),
            g.column_direction.tobytes(),
            str(f.image.dtype),
            str(f.image.shape),
            f.image.tobytes(),
        ]
    return _digest(*parts)


def study_id_for(
    source: str,
    frames: list[Frame],
    *,
    params: dict | None = None,
    path: str = '',
    study_uids: dict | None = None,
) -> str:
    """
    Return the study id of a source's frames (``TaggedFrame.study_id``).

    Parameters
    ----------
    source : str
        ``phantom``, ``pattern``, ``dicom`` or ``bag``.
    frames : list of Frame
        What the source loaded.
    params : dict, optional
        phantom/pattern: the simulation parameters (preset contents, SNR, size, phases, seed).
    path : str
        bag: the recording (its resolved path is hashed when the frames carry no study id).
    study_uids : dict, optional
        dicom: StudyInstanceUID → images (the most frequent is the study; a hash of the images
        when there is none).

    """
    if source in ('phantom', 'pattern'):
        return f'{source}-{_digest(json.dumps(params or {}, sort_keys=True, default=str))}'
    if source == 'dicom':
        return next(iter(study_uids or {}), '') or f'dicom-{images_digest(frames)}'
    carried = next((f.study_id for f in frames if f.study_id), '')
    return carried or f'bag-{_digest(Path(path).resolve())}'


def count_slices(frames: list[Frame]) -> list[Frame]:
    """
    Stamp every frame with the acquisition's SA and LA slice counts.

    Consumers use them to know when a phase is complete.
    """
    from mlv_ros.core.types import VIEW_LA, VIEW_SA

    sa = len({f.slice_index for f in frames if f.view == VIEW_SA})
    la = len({f.slice_index for f in frames if f.view == VIEW_LA})
    for f in frames:
        f.num_sa_slices, f.num_la_slices = sa, la
    return frames


class FrameSource(GraphNode):
    DIAGNOSTIC_TASK = 'input'

    def __init__(self, **node_kwargs):
        super().__init__('frame_source', **node_kwargs)
        self._declare_parameters()
        self._declare_publishing_parameters()
        # dicom: which study was taken and why, whether all of it was used, and what was not.
        self.dicom_choice, self.input_complete, self.left_out, self.not_used = '', True, [], []
        self._reports: list[tuple[str, dict]] = []  # load problems, published once someone listens
        self.pub = self.publisher(qos.FRAMES, TaggedFrame)
        self.study_uids: dict = {}  # dicom: StudyInstanceUID → images
        # phantom: renders the frames, which stay without pixels (``image`` None) until due and
        # drop them once published (the writer's history keeps what late joiners get)
        self._renderer = None
        self._rendered = 0  # frames[:_rendered] have been rendered (phantom)
        self._render_process = None  # phantom: the child simulating the frames, if any
        self._render_failure: str | None = None
        self.frames = order_frames(count_slices(self._load()), self.order)
        self.study_id = self._study_id()
        # This run: every frame carries it (a recording's frames are published anew by this run).
        self.run_id = secrets.token_hex(8)
        for f in self.frames:
            f.run_id = self.run_id
        self.study.adopt(self.study_id, self.run_id)
        self.published = 0
        self._wake = self.create_guard_condition(self._tick)  # a frame came from the renderer
        if self._renderer is not None:
            self._start_render_process()
        self.halted: str | None = None  # why publishing was stopped early (see halt)
        self.subscriber_wait = SubscriberWait(
            self.wait_for_subscribers, self.wait_timeout_s, since=time.monotonic()
        )
        self._started = None
        self._burst_at: float | None = None  # when the last burst of frames went out
        self._all_out_at: float | None = None  # when the last frame went out
        # Frames simulated in a child wake the node as they come (_wake): no need to poll often.
        fast = self._render_process is None or self.rate_factor > 0
        self.timer = self.create_timer(0.001 if fast else ACK_POLL_NS / 1e9, self._tick)
        extra = (
            {'input_complete': self.input_complete, 'left_out': len(self.left_out)}
            if self.source == 'dicom'
            else {}
        )
        self.report(
            OK,
            'frames loaded',
            source=self.source,
            frames=len(self.frames),
            order=self.order,
            problems=len(self._reports),
            study=self.study_id,
            run=self.run_id,
            **extra,
        )

    def _declare_parameters(self):
        """Declare the parameters of where frames come from: the source, its simulator or files."""
        self.source = self.param('source', 'phantom', 'where frames come from', choices=SOURCES)
        self.preset = self.param('preset', 'normal', 'simulator preset (source: phantom)')
        self.snr = self.param(
            'snr',
            20.0,
            'simulated SNR; 0 = noise-free (source: phantom)',
            min_value=0.0,
            max_value=1000.0,
        )
        self.size = self.param(
            'size',
            256,
            'simulated image size, pixels (source: phantom)',
            min_value=32,
            max_value=1024,
        )
        # 2..200: what the simulator accepts (one phase has no motion to track)
        self.num_phases = self.param(
            'num_phases',
            25,
            'simulated phases per cycle (source: phantom, pattern)',
            min_value=2,
            max_value=200,
        )
        self.seed = self.param('seed', 0, 'simulator noise seed', min_value=0, max_value=2**31 - 1)
        self.path = self.param(
            'path', '', 'DICOM directory (source: dicom) or MCAP file (source: bag)'
        )

    def _declare_publishing_parameters(self):
        """Declare the parameters of how frames go out: order, pace, waits, and DICOM limits."""
        # Phase-major by default: every slice's ED frame comes first, so registration starts at
        # once and the solver works on phase p while the tag detector tracks p + 1 (results do not
        # depend on the order). slice_major replays a study as it was acquired, cine by cine.
        self.order = self.param('order', 'phase_major', 'publication order', choices=ORDERS)
        self.rate_factor = self.param(
            'rate_factor',
            0.0,
            'real time × factor; 0 = as fast as possible',
            min_value=0.0,
            max_value=1000.0,
        )
        self.wait_for_subscribers = self.param(
            'wait_for_subscribers',
            1,
            'matched subscribers to wait for before publishing',
            min_value=0,
            max_value=100,
        )
        self.wait_timeout_s = self.param(
            'wait_timeout_s',
            30.0,
            'give up waiting for subscribers after this long',
            min_value=0.0,
            max_value=3600.0,
        )
        self.exit_when_done = self.param(
            'exit_when_done', True, 'stop the node once every frame is acknowledged'
        )
        self.max_pixels = self.param(
            'max_pixels',
            1024 * 1024,
            'largest DICOM image accepted (rows × cols); larger files are skipped before their '
            'pixels are read (source: dicom)',
            min_value=64,
            max_value=16384 * 16384,
        )
        self.dicom_study = self.param(
            'study',
            '',
            'StudyInstanceUID to load from the DICOM directory; empty = the study with the '
            'most tagged cines (source: dicom)',
        )

    def _study_id(self) -> str:
        """Return the study id every frame carries (a recording's frames keep theirs if any)."""
        params = None
        if self.source == 'phantom':
            from mlv_ros.core.sim import load_preset

            params = {
                'preset': load_preset(self.preset),
                'snr': self.snr,
                'size': self.size,
                'num_phases': self.num_phases,
                'seed': self.seed,
            }
        elif self.source == 'pattern':
            params = {'pattern': 1, 'num_phases': self.num_phases}
        study_id = study_id_for(
            self.source, self.frames, params=params, path=self.path, study_uids=self.study_uids
        )
        if len(self.study_uids) > 1:
            self._reports.append(
                (
                    'DICOM files of several studies; published as one',
                    {
                        'study': study_id,
                        'others': ', '.join(list(self.study_uids)[1:4]),
                        'images': ', '.join(map(str, self.study_uids.values())),
                    },
                )
            )
        for f in self.frames:
            f.study_id = f.study_id or study_id
        return study_id

    def _load(self) -> list[Frame]:
        if self.source == 'pattern':
            from mlv_ros.core.sim.pattern import pattern_frames

            return pattern_frames(num_phases=self.num_phases)
        if self.source == 'phantom':
            from mlv_ros.core.sim.study import StudyRenderer

            # Only the plan now: frames are simulated as they are published, in a process of
            # their own where the run may use several (_start_render_process), else here
            # (_render_ahead); the first go out while the rest are still to come.
            self._study_args = {
                'preset': self.preset,
                'snr': self.snr or None,
                'size': self.size,
                'num_phases': self.num_phases,
                'seed': self.seed,
            }
            self._renderer = StudyRenderer(**self._study_args)
            return [
                self._renderer.frame(view, index, ph, image=False)
                for view, index in self._renderer.keys
                for ph in range(self._renderer.motion.num_phases)
            ]
        if self.source == 'dicom':
            from mlv_ros.core.io.dicom import read_dicom_dir

            res = read_dicom_dir(
                self.path, max_pixels=self.max_pixels, study=self.dicom_study or None
            )
            self.dicom_choice, self.input_complete = res.choice, res.complete
            self.left_out, self.not_used = list(res.left_out), list(res.not_used)
            unused = set(res.not_used)
            self._reports += [
                ('skipped DICOM file', {'file': path, 'reason': reason})
                for path, reason in res.problems
                if (path, reason) not in unused
            ]
            self._reports += [
                ('DICOM series not used', {'file': path, 'reason': reason})
                for path, reason in res.not_used
            ]
            self._reports += [
                ('DICOM series used with a warning', {'file': path, 'reason': reason})
                for path, reason in res.warnings
            ]
            fallback = (
                bool(res.frames)
                and res.study_uid in res.studies
                and not res.studies[res.study_uid]
            )
            if len(res.studies) > 1 or self.dicom_study or not res.complete or fallback:
                self._reports.append(
                    (
                        'DICOM study chosen',
                        {
                            'choice': res.choice,
                            'complete': str(res.complete).lower(),
                            'left_out': '; '.join(why for _, why in res.left_out),
                        },
                    )
                )
            self.study_uids = dict(res.study_uids)
            return res.frames
        return read_bag_frames(self.path)

    def halt(self, reason: str) -> None:
        """
        Stop publishing now (a run being interrupted).

        Frames already sent stay sent, the rest never go out, and the node's job is over.
        """
        if self.done:
            return
        self.timer.cancel()
        if self._render_process is not None:
            self._render_process.close()
        self.halted = reason
        self.report(
            OK,
            'input stopped',
            reason=reason,
            frames_published=self.published,
            frames=len(self.frames),
        )
        self.stop()

    def _frame_interval(self, frame: Frame) -> float:
        if self.rate_factor <= 0 or frame.num_phases == 0:
            return 0.0
        cycle = frame.cycle_duration or 1.0
        return cycle / frame.num_phases / self.rate_factor

    def _start_render_process(self) -> None:
        """Simulate the phantom's frames in a child process, in publication order (if allowed)."""
        from mlv_ros.render_process import processes_allowed, RenderProcess

        if not processes_allowed():
            return
        keys = [(f.view, f.slice_index, f.phase_index) for f in self.frames]
        self._render_process = RenderProcess(
            self._study_args, keys, self._frame_rendered, self._render_failed
        )

    def _frame_rendered(self, index: int, image) -> None:
        """Take frame ``index``'s image from the render process (its reader thread)."""
        self.frames[index].image = image
        self._rendered = index + 1
        self._wake_up()

    def _render_failed(self, reason: str) -> None:
        """Note that the render process failed (its reader thread): the rest is rendered here."""
        self._render_failure = reason
        self._wake_up()

    def _wake_up(self) -> None:
        """Have the executor run :meth:`_tick` (from the render process's reader thread)."""
        try:
            self._wake.trigger()
        except InvalidHandle:
            pass  # the node is being destroyed: nothing is published any more

    def _ready(self) -> int:
        """
        Return how many frames (from the first) can be published now.

        A failed render process is reported here (once) and ended: from then on frames are
        simulated in this process as they are published.
        """
        if self._render_process is None:
            return len(self.frames)  # rendered here as they are published
        if self._render_failure is not None:
            self.report(
                OK,
                'frames are simulated in this process from here on',
                reason=self._render_failure,
                frames_simulated=self._rendered,
            )
            self._render_process.close()
            self._render_process = self._render_failure = None
            return len(self.frames)
        return self._rendered

    def destroy_node(self):
        """End the render process, if any, with the node."""
        if self._render_process is not None:
            self._render_process.close()
        return super().destroy_node()

    def _render_ahead(self) -> bool:
        """
        Render the next frame not yet rendered (phantom); return whether there was one.

        Called for the next frame due, and while the source waits (for subscribers, for a burst
        to be acknowledged) so that waiting time simulates frames to come.
        """
        if (
            self._renderer is None
            or self._render_process is not None
            or self._rendered >= len(self.frames)
        ):
            return False
        f = self.frames[self._rendered]
        f.image = self._renderer.frame(f.view, f.slice_index, f.phase_index).image
        self._rendered += 1
        return True

    def _publish_next(self) -> None:
        """Publish the next frame, stamped now, and schedule the one after it."""
        frame = self.frames[self.published]
        if self._rendered == self.published:
            self._render_ahead()
        self.pub.publish(conversions.frame_to_msg(frame, stamp=self.get_clock().now().to_msg()))
        if self._renderer is not None:
            frame.image = None
        self.published += 1
        if self._render_process is not None:
            self._render_process.taken()  # dropped: the render process may hand over one more
        self._next_at += self._frame_interval(frame)

    def _publish_due(self) -> None:
        """
        Publish the frame that is due (``rate_factor`` > 0), or the next :data:`BURST_FRAMES`.

        A burst starts only once every frame of the previous one is acknowledged by every
        subscriber (or ``wait_timeout_s`` after it went out), so at most ``BURST_FRAMES`` frames
        are ever unacknowledged in the KEEP_LAST(``STREAM_DEPTH``) writer history and none is
        dropped before each reader holds it, whatever the study's size.
        """
        now = time.monotonic()
        ready = self._ready()
        if self.rate_factor > 0:  # a paced stream, as a scanner sends it: one frame when due
            if now >= self._next_at and ready > self.published:
                self._publish_next()
            else:
                self._render_ahead()
            return
        if self._burst_at is not None and not self.pub.wait_for_all_acked(Duration()):
            if now - self._burst_at < self.wait_timeout_s:
                self._render_ahead()
                return
            self.report(
                WARN,
                'frames not acknowledged by every subscriber; publishing on',
                timeout_s=self.wait_timeout_s,
                frames_published=self.published,
            )
        if ready == self.published:
            return  # the next frame is still being simulated: its arrival wakes the node
        self._burst_at = now
        for _ in range(min(BURST_FRAMES, ready - self.published)):
            self._publish_next()

    def _tick(self):
        if self.timer.is_canceled():
            return  # woken by the render process after the node's job ended
        if self._started is None:
            matched = self.pub.get_subscription_count()
            # Reports made before anyone listens on /diagnostics (VOLATILE) would be lost: with
            # problems to report, wait for a listener there too (the recorder, a monitor).
            heard = (
                not self._reports
                or not self.wait_for_subscribers
                or self.count_subscribers(qos.DIAGNOSTICS) > 0
            )
            wait = self.subscriber_wait.poll(matched, ready=heard)
            if wait == SubscriberWait.WAIT:
                self._render_ahead()
                return
            if wait == SubscriberWait.LATE and matched == 0:
                self.report(
                    ERROR, 'no subscriber appeared; not publishing', waited_s=self.wait_timeout_s
                )
                self.timer.cancel()
                self.blocked = 1  # frames left that no one will take
                self.stop()
                return
            if wait == SubscriberWait.LATE:
                # Frames are kept for late joiners (TRANSIENT_LOCAL), but a VOLATILE subscriber
                # that appears later misses them: say so rather than wait for ever.
                self.subscriber_wait.go_on(self, matched)
            self._started = time.monotonic()
            self._next_at = self._started
        if self._reports:
            # One per tick, so that a /diagnostics reader keeps up with hundreds (ours keep 1000,
            # diagnostic_updater's tools 100).
            message, values = self._reports.pop(0)
            self.report(WARN, message, **values)
            return
        if self.published < len(self.frames):
            self._publish_due()
            return
        # RELIABLE: make sure every subscriber holds every frame before we may exit. Polled, not
        # waited for: a blocking wait would hold the executor the other nodes share for seconds.
        now = time.monotonic()
        if self._all_out_at is None:
            self._all_out_at = now
            self.timer.timer_period_ns = ACK_POLL_NS
        acked = self.pub.wait_for_all_acked(Duration())
        if not acked and now - self._all_out_at < self.wait_timeout_s:
            return
        self.timer.cancel()
        if not acked:
            self.report(
                WARN,
                'not every frame was acknowledged by every subscriber',
                timeout_s=self.wait_timeout_s,
            )
        self.report(
            OK,
            'all frames published',
            frames=self.published,
            seconds=round(time.monotonic() - self._started, 3),
            publish_s=round(self._all_out_at - self._started, 3),
        )
        if self.exit_when_done:
            self.stop()


def main(args=None):
    return run_node(FrameSource, args)


if __name__ == '__main__':
    raise SystemExit(main())

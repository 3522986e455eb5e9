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
tag_detector: tag intersections per frame, tracked through each slice's cine.

``/mlv/frames`` → ``/mlv/tag_points``.

One :class:`~mlv_ros.core.tags.SliceTracker` per (view, slice). Frames may arrive in any order
(slice-major, phase-major, interleaved); each slice's frames are processed in phase order, later
phases waiting until their predecessor arrives. A phase that has not arrived while
``max_pending`` later ones wait is declared missing (reported on /diagnostics) and skipped.
Duplicates are dropped (a different image for a filled slot with a warning). A frame that cannot
be used, when it is the next one its slice expects, still yields a TagPoints message (empty,
``status`` = reason), so downstream knows the slice was seen; an unusable frame for a slot already
filled or still open further on is only reported (a corrupt copy must not replace or pre-empt the
real frame). The first usable frame fixes the study (``study_id``) and its dimensions (phases,
slice counts); a frame of another study (a second graph on the ROS domain) is reported and
ignored, one contradicting the dimensions is refused. Tag points carry their frame's study. Every
report about a frame names it: view, slice, phase and header stamp.

What is said how loud: tags fade over the cycle and lines leave the slab, so tracks ending and
frames with few or no points are routine; they are DEBUG lines and counts in the 1 Hz heartbeat
(``frames_with_ended_tracks``, ``frames_without_points``, ``tracks_alive``...). WARN/ERROR only
for what a user must look at: a refused or unusable frame, a slice whose ED detection failed (said
once; its later frames are counted), an ED frame that could not be segmented, a frame that never
came, a different image for a filled slot. The heartbeat's level and message keep naming those
until the run ends.
"""

from __future__ import annotations

from collections import Counter
import hashlib

from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.streaming import InOrderBuffer
from mlv_ros.core.tags import LineSliceTracker, SliceTracker
from mlv_ros.core.tags.gabor import TagInputError, validate_image
from mlv_ros.core.types import TagPointSet, TAGS_GRID
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, WARN

VIEW_NAME = {TaggedFrame.VIEW_SA: 'SA', TaggedFrame.VIEW_LA: 'LA'}


def _slice_name(key) -> str:
    return f'{VIEW_NAME.get(key[0], key[0])} {key[1]}'


def _digest(msg: TaggedFrame) -> bytes:
    """Return what tells a re-sent frame from a different one in the same slot."""
    h = hashlib.blake2b(digest_size=16)
    h.update(f'{msg.image.encoding} {msg.image.height}x{msg.image.width}'.encode())
    h.update(bytes(msg.image.data))
    return h.digest()


class TagDetector(GraphNode):
    DIAGNOSTIC_TASK = 'tag tracking'

    def __init__(self, **node_kwargs):
        super().__init__('tag_detector', **node_kwargs)
        self.spacing_px = self.param(
            'spacing_px',
            0.0,
            'tag spacing override, pixels (0 = estimate from the ED spectrum)',
            min_value=0.0,
            max_value=100.0,
        )
        self.max_pending = self.param(
            'max_pending',
            3,
            'later phases allowed to wait for a missing one',
            min_value=1,
            max_value=100,
        )
        self.max_pixels = self.param(
            'max_pixels',
            1024 * 1024,
            'largest image accepted (rows × cols)',
            min_value=64,
            max_value=16384 * 16384,
        )
        self.catch_up = self.param(
            'catch_up',
            True,
            'take frames with their history (TRANSIENT_LOCAL), so a restart '
            'gets the frames already sent; false for a publisher without history',
        )
        self.register = self.param(
            'tracking.register',
            True,
            'move each tracked tag point to where its own ED neighbourhood registers in the '
            'image (local affine map; corrects the pull of the tag filter toward mid-wall)',
        )
        self.pub = self.publisher(qos.TAG_POINTS, TagPoints)
        self.subscribe(qos.FRAMES, TaggedFrame, self._on_frame, catch_up=self.catch_up)
        self.masker = StreamingMasker()  # ED myocardium masks from what has streamed in so far
        self.trackers: dict = {}  # (view, slice) → SliceTracker
        self.order = InOrderBuffer(self.max_pending)  # each slice's frames in phase order
        self.messages_handled = 0
        self.published = 0  # tag point sets published (one a frame)
        self.digests: dict = {}  # (view, slice, phase) → image digest of the frame taken
        self.counts = Counter()  # routine and notable events, carried by the heartbeat
        self.no_tags: dict = {}  # (view, slice) → why its ED detection failed
        self.report(OK, 'ready')

    def _on_frame(self, msg: TaggedFrame) -> None:
        self.messages_handled += 1
        where = f'view {msg.view} slice {msg.slice_index} phase {msg.phase_index}'
        stamp = conversions.stamp_text(msg.header.stamp)
        try:
            self._take(msg, where, stamp)
        finally:
            self._update_status()

    def _take(self, msg: TaggedFrame, where: str, stamp: str) -> None:
        if self.foreign(msg.study_id, qos.FRAMES, run_id=msg.run_id, frame=where, stamp=stamp):
            return  # another graph's frame: nothing of it goes downstream
        if msg.image.height * msg.image.width > self.max_pixels:
            self.counts['frames_refused'] += 1
            self.report(
                ERROR,
                'frame refused: image too large',
                frame=where,
                stamp=stamp,
                size=f'{msg.image.height}x{msg.image.width}',
                limit=self.max_pixels,
            )
            return self._publish_empty(msg, 'image too large')
        try:
            frame = conversions.msg_to_frame(msg, allow_nonfinite=True)
            self.study.check(frame)
        except ValueError as exc:
            self.counts['frames_refused'] += 1
            self.report(ERROR, 'bad frame', frame=where, stamp=stamp, reason=str(exc))
            return self._publish_empty(msg, f'bad frame: {exc}')
        key = (frame.view, frame.slice_index)
        self.masker.observe_geometry(frame)
        slot = (*key, frame.phase_index)
        digest = _digest(msg)
        if not self.order.offer(key, frame.phase_index, (frame, msg.header.stamp)):
            self._duplicate(slot, digest, where, stamp)
            return
        self.digests[slot] = digest
        self._drain(key)

    def _duplicate(self, slot, digest: bytes, where: str, stamp: str) -> None:
        known = self.digests.get(slot)
        if known is None:
            # Its slot was given up (skipped as missing, or filled in for a refused frame).
            self.counts['late_frames_dropped'] += 1
            self.report(
                WARN, 'frame came after its slot was given up; dropped', frame=where, stamp=stamp
            )
            return
        if known != digest:
            # Same slot, other pixels: a second study on this ROS domain, or a source sending
            # two acquisitions as one. The first frame stays; the user must find out why.
            self.counts['conflicting_frames'] += 1
            self.report(
                WARN,
                'a different frame for a slot already taken; dropped (another study on '
                'this ROS_DOMAIN_ID?)',
                frame=where,
                stamp=stamp,
            )
            return
        # A re-sent copy (a restarted source replays its history) changes nothing: said once.
        self.counts['duplicates_dropped'] += 1
        if self.counts['duplicates_dropped'] == 1:
            self.report(
                OK,
                'duplicate frame dropped (further ones are counted in the heartbeat)',
                frame=where,
                stamp=stamp,
            )
        else:
            self.get_logger().debug(f'duplicate frame dropped frame={where} stamp={stamp}')

    def _drain(self, key) -> None:
        """Process the slice's frames that are due, in phase order (the missing ones skipped)."""
        for slot in self.order.drain(key):
            if slot.item is None:
                self.counts['frames_missing'] += 1
                self.report(
                    WARN, 'frame missing; skipped', view=key[0], slice=key[1], phase=slot.phase
                )
            else:
                self._process(key, *slot.item)

    def _process(self, key, frame, stamp) -> None:
        tracker = self.trackers.get(key)
        mask = None
        started = tracker is None or frame.phase_index == 0
        if started:
            tracker = self.trackers[key] = self._tracker(frame)
            self.no_tags.pop(key, None)
            mask, why = self.masker.ed_mask(frame)
        points = tracker.update(frame, mask=mask)
        points.num_sa_slices, points.num_la_slices = frame.num_sa_slices, frame.num_la_slices
        points.study_id, points.run_id = frame.study_id, frame.run_id
        if started and mask is None and tracker.params is not None:
            # Its tag points may include blood or background: worth a look, once. (Without a
            # grid at ED the slice gives no points at all, and that is what _judge says.)
            self.counts['slices_without_mask'] += 1
            self.report(
                WARN,
                'no ED myocardium mask; detecting on tag energy alone',
                view=key[0],
                slice=key[1],
                reason=why,
            )
        if started:
            self._pair_shift(key, tracker)
        self._judge(key, frame, points, started, conversions.stamp_text(stamp))
        self.pub.publish(conversions.tagpoints_to_msg(points, stamp=stamp))
        self.published += 1

    def _pair_shift(self, key, tracker) -> None:
        """Count a line pair's breath-hold shift (DEBUG); WARN once when it degrades the slice."""
        shift = getattr(tracker, 'pair_shift', None)
        if shift is None:
            return
        if shift.sure:
            self.counts['line_pairs_shift_corrected'] += 1
            self.get_logger().debug(
                f'line pair view={key[0]} slice={key[1]}: second series shifted '
                f'{shift.shift_mm:.2f} mm in-plane (rows, cols {shift.shift_rc[0]:+.2f}, '
                f'{shift.shift_rc[1]:+.2f} px, correlation {shift.score:.3f}); corrected'
            )
        if tracker.pair_note:
            self.counts['line_pairs_misregistered'] += 1
            self.report(WARN, 'line pair', view=key[0], slice=key[1], status=tracker.pair_note)

    def _tracker(self, frame):
        """
        Return a new tracker for the slice of ``frame`` (its first frame or its ED frame).

        A tag grid's intersections (:class:`SliceTracker`), or the points on single tag lines
        of a single-line study (``tag_lines``: one family or a line pair,
        :class:`LineSliceTracker`; it reads tags only inside the ED myocardium mask).
        """
        if frame.tag_lines != TAGS_GRID:
            return LineSliceTracker(frame.geometry, spacing_px=self.spacing_px or None)
        return SliceTracker(
            frame.geometry, spacing_px=self.spacing_px or None, register=self.register
        )

    def _judge(self, key, frame, points: TagPointSet, started: bool, stamp: str) -> None:
        """Say what a user must act on at WARN; count and DEBUG-log what tags do anyway."""
        n_ed = len(points) if started else len(self.trackers[key].track_id)
        if started and self.trackers[key].params is None:
            # No grid read at ED: this slice gives no tag points for the whole cine.
            self.no_tags[key] = points.status
            self.report(
                WARN,
                'tag detection',
                view=key[0],
                slice=key[1],
                phase=frame.phase_index,
                stamp=stamp,
                points=0,
                status=points.status + '; this slice gives no tag points',
            )
            return
        if key in self.no_tags:  # already said once; its later frames cannot add tag points
            self.counts['frames_in_slices_without_tags'] += 1
            self.get_logger().debug(
                f'tag detection view={key[0]} slice={key[1]} phase={frame.phase_index} '
                f'stamp={stamp} status={points.status}'
            )
            return
        unusable = ''
        if points.status and not started:
            try:
                validate_image(frame.image)
            except TagInputError as exc:
                unusable = str(exc)
        if unusable or points.status.startswith('tag tracker error'):
            self.counts['unusable_frames'] += 1
            self.report(
                WARN,
                'tag detection',
                view=key[0],
                slice=key[1],
                phase=frame.phase_index,
                stamp=stamp,
                points=len(points),
                status=points.status,
            )
            return
        if len(points) == 0:
            self.counts['frames_without_points'] += 1
        elif len(points) < n_ed:
            self.counts['frames_with_ended_tracks'] += 1
        if points.status:
            self.get_logger().debug(
                f'tag detection view={key[0]} slice={key[1]} phase={frame.phase_index} '
                f'stamp={stamp} points={len(points)} status={points.status}'
            )

    def _update_status(self) -> None:
        """
        Update the heartbeat's status: the counts, at OK unless something needs the user's eye.

        Set without publishing or logging (the heartbeat republishes it every second); events
        that need saying were already reported when they happened.
        """
        c = self.counts
        problems = []
        lost = sum(s.lost for s in self.streams.values())
        if lost:
            problems.append(f'{lost} message(s) lost in transport')
        if c['frames_refused']:
            problems.append(f'{c["frames_refused"]} frame(s) refused')
        level = ERROR if problems else OK
        if self.no_tags:
            problems.append(
                f'no tag points from {", ".join(map(_slice_name, sorted(self.no_tags)))} '
                '(ED detection failed)'
            )
        for name, what in (
            ('unusable_frames', 'unusable frame(s)'),
            ('frames_missing', 'frame(s) never came'),
            ('conflicting_frames', 'different frame(s) for a taken slot'),
            ('late_frames_dropped', 'frame(s) too late for their slot'),
            ('slices_without_mask', 'slice(s) without an ED myocardium mask'),
            ('line_pairs_misregistered', 'line pair(s) misregistered (degraded)'),
        ):
            if c[name]:
                problems.append(f'{c[name]} {what}')
        level = max(level, WARN) if problems else OK
        ed_tracks = sum(len(t.track_id) for t in self.trackers.values())
        alive = sum(len(t.alive) for t in self.trackers.values())
        values = {
            'frames': self.published,
            'slices': len(self.trackers),
            'tracks_at_ed': ed_tracks,
            'tracks_alive': alive,
            **dict(sorted(c.items())),
        }
        message = (
            '; '.join(problems)
            if problems
            else f'tracking: {self.published} frames, {len(self.trackers)} slices'
        )
        status = self.diagnostic_status(level, message, values)
        # GraphNode's heartbeat republishes _status (with the per-topic stream counts) at 1 Hz.
        self._status = status

    def _publish_empty(self, msg: TaggedFrame, reason: str) -> None:
        """
        Publish an empty set standing in for a frame that could not be used, if it may.

        Only if the frame's indices are usable and its slot is the next one its slice expects (a
        filled or later slot keeps its own).
        """
        key = (msg.view, msg.slice_index)
        if not self.order.expects(key, msg.phase_index):
            return
        try:
            geometry = conversions.msg_to_geometry(msg.geometry)
            points = TagPointSet(
                view=msg.view,
                slice_index=msg.slice_index,
                phase_index=msg.phase_index,
                num_phases=msg.num_phases,
                geometry=geometry,
                status=reason,
                num_sa_slices=msg.num_sa_slices,
                num_la_slices=msg.num_la_slices,
                study_id=msg.study_id,
                run_id=msg.run_id,
            )
            out = conversions.tagpoints_to_msg(points, stamp=msg.header.stamp)
        except ValueError:
            return  # geometry or indices unusable: nothing meaningful to forward
        self.order.fill(key, msg.phase_index)
        self.pub.publish(out)
        self.published += 1
        self._drain(key)  # later phases that waited for this slot go on


def main(args=None):
    return run_node(TagDetector, args)


if __name__ == '__main__':
    raise SystemExit(main())

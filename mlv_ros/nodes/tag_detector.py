"""tag_detector: tag intersections per frame, tracked through each slice's cine
(``/mlv/frames`` → ``/mlv/tag_points``).

One :class:`~mlv_ros.core.tags.SliceTracker` per (view, slice). Frames may arrive in any order
(slice-major, phase-major, interleaved); each slice's frames are processed in phase order, later
phases waiting until their predecessor arrives. A phase that has not arrived while
``max_pending`` later ones wait is declared missing (reported on /diagnostics) and skipped.
Duplicates are dropped with a warning. A frame that cannot be used, when it is the next one its
slice expects, still yields a TagPoints message (empty, ``status`` = reason), so downstream knows
the slice was seen; an unusable frame for a slot already filled or still open further on is only
reported (a corrupt copy must not replace or pre-empt the real frame). The first usable frame
fixes the study's dimensions (phases, slice counts); a frame contradicting them is refused.
Every report about a frame names it: view, slice, phase and header stamp.
"""

from __future__ import annotations


from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.tags import SliceTracker
from mlv_ros.core.types import StudyShape, TagPointSet
from mlv_ros.nodes.common import ERROR, OK, WARN, GraphNode, run_node


class TagDetector(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("tag_detector", **node_kwargs)
        self.spacing_px = self.param("spacing_px", 0.0, "tag spacing override, pixels (0 = estimate from the ED spectrum)", min_value=0.0, max_value=100.0)
        self.max_pending = self.param("max_pending", 3, "later phases allowed to wait for a missing one", min_value=1, max_value=100)
        self.max_pixels = self.param("max_pixels", 1024 * 1024, "largest image accepted (rows × cols)", min_value=64, max_value=16384 * 16384)
        self.catch_up = self.param("catch_up", True, "take frames with their history (TRANSIENT_LOCAL), so a restart "
                                   "gets the frames already sent; false for a publisher without history")
        self.pub = self.create_publisher(TagPoints, qos.TAG_POINTS, qos.topic_qos(qos.TAG_POINTS))
        self.create_subscription(TaggedFrame, qos.FRAMES, self._on_frame, qos.subscription_qos(qos.FRAMES, catch_up=self.catch_up))
        self.masker = StreamingMasker()  # ED myocardium masks from what has streamed in so far
        self.trackers: dict = {}   # (view, slice) → SliceTracker
        self.next_phase: dict = {}  # (view, slice) → next phase to process
        self.pending: dict = {}    # (view, slice) → {phase: (frame, stamp)}
        self.study = StudyShape()
        self.messages_handled = 0
        self.frames_out = 0
        self.report(OK, "ready")

    def _on_frame(self, msg: TaggedFrame) -> None:
        self.messages_handled += 1
        where = f"view {msg.view} slice {msg.slice_index} phase {msg.phase_index}"
        stamp = conversions.stamp_text(msg.header.stamp)
        if msg.image.height * msg.image.width > self.max_pixels:
            self.report(ERROR, "frame refused: image too large", frame=where, stamp=stamp,
                        size=f"{msg.image.height}x{msg.image.width}", limit=self.max_pixels)
            return self._publish_empty(msg, "image too large")
        try:
            frame = conversions.msg_to_frame(msg, allow_nonfinite=True)
            self.study.check(frame)
        except ValueError as exc:
            self.report(ERROR, "bad frame", frame=where, stamp=stamp, reason=str(exc))
            return self._publish_empty(msg, f"bad frame: {exc}")
        key = (frame.view, frame.slice_index)
        self.masker.observe_geometry(frame)
        nxt = self.next_phase.setdefault(key, 0)
        waiting = self.pending.setdefault(key, {})
        if frame.phase_index < nxt or frame.phase_index in waiting:
            self.report(WARN, "duplicate frame dropped", frame=where, stamp=stamp)
            return
        waiting[frame.phase_index] = (frame, msg.header.stamp)
        self._drain(key)

    def _drain(self, key) -> None:
        waiting = self.pending[key]
        while waiting:
            nxt = self.next_phase[key]
            if nxt not in waiting:
                if len(waiting) < self.max_pending:
                    return
                self.report(WARN, "frame missing; skipped", view=key[0], slice=key[1], phase=nxt)
                self.next_phase[key] = nxt + 1
                continue
            frame, stamp = waiting.pop(nxt)
            self.next_phase[key] = nxt + 1
            self._process(key, frame, stamp)

    def _process(self, key, frame, stamp) -> None:
        tracker = self.trackers.get(key)
        mask = None
        if tracker is None or frame.phase_index == 0:
            tracker = self.trackers[key] = SliceTracker(frame.geometry, spacing_px=self.spacing_px or None)
            mask, why = self.masker.ed_mask(frame)
            if mask is None:
                self.report(WARN, "no ED myocardium mask; detecting on tag energy alone", view=key[0],
                            slice=key[1], reason=why)
        points = tracker.update(frame, mask=mask)
        points.num_sa_slices, points.num_la_slices = frame.num_sa_slices, frame.num_la_slices
        if points.status:
            self.report(WARN, "tag detection", view=key[0], slice=key[1], phase=frame.phase_index,
                        stamp=conversions.stamp_text(stamp), points=len(points), status=points.status)
        self.pub.publish(conversions.tagpoints_to_msg(points, stamp=stamp))
        self.frames_out += 1

    def _publish_empty(self, msg: TaggedFrame, reason: str) -> None:
        """An empty set standing in for a frame that could not be used, if its indices are usable
        and its slot is the next one its slice expects (a filled or later slot keeps its own)."""
        key = (msg.view, msg.slice_index)
        if msg.phase_index != self.next_phase.get(key, 0) or msg.phase_index in self.pending.get(key, {}):
            return
        try:
            geometry = conversions.msg_to_geometry(msg.geometry)
            points = TagPointSet(view=msg.view, slice_index=msg.slice_index, phase_index=msg.phase_index,
                                 num_phases=msg.num_phases, geometry=geometry, status=reason,
                                 num_sa_slices=msg.num_sa_slices, num_la_slices=msg.num_la_slices)
            out = conversions.tagpoints_to_msg(points, stamp=msg.header.stamp)
        except ValueError:
            return  # geometry or indices unusable: nothing meaningful to forward
        self.next_phase[key] = msg.phase_index + 1
        self.pub.publish(out)
        self.frames_out += 1
        if key in self.pending:
            self._drain(key)  # later phases that waited for this slot go on


def main(args=None):
    return run_node(TagDetector, args)


if __name__ == "__main__":
    raise SystemExit(main())

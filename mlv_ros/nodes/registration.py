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
registration: registers the meshless model to the end-diastolic images.

``/mlv/frames`` → ``/mlv/registered_cloud``, ``/mlv/registered_state``, both latched.

Collects the ED frame (phase 0) of every slice; once all ``num_sa_slices + num_la_slices`` are
in, or ``ed_timeout_s`` after the first one with at least ``min_sa_slices``, segments them,
reconstructs the myocardium, samples particles and registers the model (paper §3.2, Fig. 7).
The cloud carries each particle's position and its polar model coordinates (α, β, w) and
transmural depth, so the solver rebuilds exactly the same model.

The first ED frame taken fixes the study (``study_id``, carried on by the registered state);
frames of another study are reported and ignored. Registration happens once a run, so what it
has to say is said once: the final ``registered``
status is WARN, with every warning in it, when the model was built with something missing (slices
that could not be segmented, no LA view...); a re-sent identical ED frame is only a DEBUG line.
"""

from __future__ import annotations

import time

from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import TaggedFrame
from mlv_ros import conversions, qos
from mlv_ros.core.types import RegisteredModel, SEGMENT_ORIGIN_CODES, VIEW_SA
from mlv_ros.core.verdict import registration_verdict
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, Silence, WARN
from mlv_ros.settings import REGISTRATION
import numpy as np
from sensor_msgs.msg import PointCloud2

CHECK_PERIOD_S = 0.25  # how often the ED timeout is looked at


class Registration(GraphNode):
    DIAGNOSTIC_TASK = 'ED registration'

    def __init__(self, **node_kwargs):
        super().__init__('registration', **node_kwargs)
        self.declare_settings(REGISTRATION)  # self.num_particles, self.seed ...
        self.cloud_pub = self.publisher(qos.REGISTERED_CLOUD, PointCloud2)
        self.state_pub = self.publisher(qos.REGISTERED_STATE, ModelStateMsg)
        self.subscribe(qos.FRAMES, TaggedFrame, self._on_frame, catch_up=self.catch_up)
        self.ed_frames: dict = {}
        self.expected = 0
        self.first_at = None
        self.silence = Silence(
            CHECK_PERIOD_S
        )  # on the frame stream, counted while this node is spun
        self.registered = False
        self.result = None
        self.verdict = None  # registration_verdict of the ED model, once registered
        self.messages_handled = 0
        self.create_timer(CHECK_PERIOD_S, self._check_timeout)
        self.report(OK, 'waiting for ED frames')

    def _on_frame(self, msg: TaggedFrame) -> None:
        self.messages_handled += 1
        if self.foreign_slice_message(msg, qos.FRAMES):
            return  # another graph's frame (nor does it count as activity on our stream)
        self.silence.heard()
        if msg.phase_index != 0 or self.registered:
            return
        frame = self.converted(
            msg,
            lambda m: conversions.msg_to_frame(m, allow_nonfinite=True),
            'bad ED frame ignored',
            check_study=True,
            view=msg.view,
            slice=msg.slice_index,
        )
        if frame is None:
            return
        key = (frame.view, frame.slice_index)
        if key in self.ed_frames:
            old = self.ed_frames[key]
            if old.image.shape == frame.image.shape and np.array_equal(
                old.image, frame.image, equal_nan=True
            ):
                # A re-sent copy (a restarted source replays its history): nothing changes.
                self.get_logger().debug(
                    f'identical ED frame received again view={key[0]} slice={key[1]}'
                )
            else:
                self.report(
                    WARN,
                    'a different ED frame for a slice already received replaces it (another '
                    'study on this ROS_DOMAIN_ID?)',
                    view=key[0],
                    slice=key[1],
                    stamp=conversions.stamp_text(msg.header.stamp),
                )
        self.ed_frames[key] = frame
        self.expected = max(self.expected, frame.num_sa_slices + frame.num_la_slices)
        self.first_at = self.first_at or time.monotonic()
        if self.expected and len(self.ed_frames) >= self.expected:
            self._register()

    def _check_timeout(self) -> None:
        # Slices stream one cine at a time, so later slices' ED frames can be far apart: only
        # silence on the frame stream means the missing ones are not coming.
        silent = self.silence.tick()
        if self.registered or self.first_at is None or silent < self.ed_timeout_s:
            return
        sa = sum(1 for v, _ in self.ed_frames if v == VIEW_SA)
        if sa >= self.min_sa_slices:
            self.report(
                WARN,
                'registering without every ED slice',
                have=len(self.ed_frames),
                expected=self.expected,
            )
            self._register()

    def _register(self) -> None:
        from mlv_ros.core.registration import register_ed

        self.registered = True
        t0 = time.monotonic()
        frames = list(self.ed_frames.values())
        masks = self._user_masks(frames)
        try:
            res = register_ed(
                frames, num_particles=self.num_particles, seed=self.seed, masks=masks
            )
        except ValueError as exc:
            self.report(ERROR, 'registration failed', reason=str(exc), slices=len(self.ed_frames))
            self.blocked = 1  # it registers once: nothing follows in this run
            return
        left_out = [
            f'{"SA" if rep.view == VIEW_SA else "LA"} {rep.slice_index}: {rep.reason}'
            for rep in res.slice_reports
            if not rep.ok
        ]
        self.result = res
        stamp = self.get_clock().now().to_msg()
        state, verdict, septum = self._state_of(res)
        model = RegisteredModel(
            res.particles,
            res.polar['alpha'],
            res.polar['beta'],
            res.polar['w'],
            state,
            res.polar.get('transmural'),
        )
        cloud_msg, state_msg = conversions.registered_to_msgs(model, stamp)
        self.cloud_pub.publish(cloud_msg)
        self.state_pub.publish(state_msg)
        extra = {}
        if res.warnings:
            extra['warnings'] = ' | '.join(res.warnings)
        if left_out:
            extra['not_segmented'] = '; '.join(left_out)
        if verdict.level:
            extra['verdict'] = f'{verdict.name}: {verdict.text}'
        # Where the AHA segments' origin came from; not a warning (nothing to act on), but said.
        where = {}
        if septum is not None:
            where['segment_origin'] = (
                f'RV detected on {septum.slices_used} of {septum.slices_total} SA slices '
                f'(confidence {septum.confidence:.2f})'
                if septum.source == 'detected'
                else f'{septum.source}: not tied to the anatomy ({septum.reason})'
            )
        self.report(
            WARN if extra else OK,
            'registered',
            **where,
            particles=len(res.particles),
            slices=len(self.ed_frames),
            seconds=round(time.monotonic() - t0, 2),
            residual_mm=round(float(state.residual), 3),
            **extra,
        )

    def _user_masks(self, frames: list):
        """Return the user's ED masks of the frames (None without), reporting what they miss."""
        masks = None
        if self.mask_path:
            from mlv_ros.core.registration.nifti import masks_for_frames

            try:
                masks, reasons = masks_for_frames(self.mask_path, frames, label=self.mask_label)
            except ValueError as exc:
                self.report(
                    ERROR,
                    'user mask unusable; segmenting automatically',
                    path=self.mask_path,
                    reason=str(exc),
                )
            else:
                if reasons:  # one line for all of them: the same fix (the mask file) for each
                    self.report(
                        WARN,
                        'the user mask does not cover every slice; segmenting those automatically',
                        path=self.mask_path,
                        slices='; '.join(
                            f'{"SA" if view == VIEW_SA else "LA"} {idx}: {why}'
                            for (view, idx), why in sorted(reasons.items())
                        ),
                    )
        return masks

    def _state_of(self, res):
        """Complete the registration's model state: phases, verdict, study and segment origin."""
        state = res.state
        state.num_phases = state.num_phases or max(f.num_phases for f in self.ed_frames.values())
        verdict = self.verdict = registration_verdict(res.slice_reports, res.wall_thickness_mm())
        state.verdict, state.verdict_reasons = verdict.level, verdict.text
        state.study_id, state.run_id = self.study.study_id, self.study.run_id
        septum = res.septum
        if septum is not None:
            state.segment_origin = SEGMENT_ORIGIN_CODES[septum.source]
            state.segment_origin_confidence = float(np.clip(septum.confidence, 0.0, 1.0))
        return state, verdict, septum


def main(args=None):
    return run_node(Registration, args)


if __name__ == '__main__':
    raise SystemExit(main())

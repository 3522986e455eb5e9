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
meshless_solver: dense LV motion phase by phase.

``/mlv/tag_points`` + the registered model → ``/lv/motion``, ``/lv/model_state``.

Tag point sets are assembled per phase as slices arrive, in any order (a duplicate replaces its
earlier copy). Phase t is solved as soon as every slice's set is in — warm-started from t−1 —
or, when a slice never comes, once a later phase is complete or no input has arrived for
``incomplete_timeout_s`` (with a warning naming what is missing). ``/lv/motion`` carries, per
particle: ``x, y, z`` position at this phase (patient mm), ``dx, dy, dz`` displacement from ED
(mm) and Green–Lagrange strain components ``err, ecc, ell`` (radial, circumferential,
longitudinal, relative to ED).

Run isolation: the node keeps to the study of the first registered state or tag point set it
takes (``study_id``), and reports and ignores messages of another. The registered cloud cannot
carry a study, so it is used with the registered state of the same header stamp (the
registration stamps both alike); a cloud whose state is of another study is dropped with it.
Published model states carry the study.
"""

from __future__ import annotations

import time

from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.analysis import cardiac_coordinates, cardiac_strain, LVFrame
from mlv_ros.core.analysis.frame import lv_frame_axes, plane_level_span
from mlv_ros.core.streaming import PhaseSchedule
from mlv_ros.core.tracking import MotionTracker
from mlv_ros.core.verdict import LEVEL_NAMES
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, Silence, SubscriberWait, WARN
from mlv_ros.settings import SOLVER_MODEL, SOLVER_STREAM
import numpy as np
from sensor_msgs.msg import PointCloud2

TIMER_PERIOD_S = 0.2  # how often waits (incomplete phases, outputs) are looked at


class MeshlessSolver(GraphNode):
    DIAGNOSTIC_TASK = 'motion solve'

    def __init__(self, **node_kwargs):
        super().__init__('meshless_solver', **node_kwargs)
        # Each setting becomes an attribute named by its core keyword (self.twist_knots ...).
        self.declare_settings(SOLVER_MODEL + SOLVER_STREAM)
        self.subscriber_wait = SubscriberWait(self.wait_for_subscribers, self.wait_timeout_s)
        self.motion_pub = self.publisher(qos.MOTION, PointCloud2)
        self.state_pub = self.publisher(qos.MODEL_STATE, ModelStateMsg)
        self.subscribe_registration(self._build)  # self.registered
        self.subscribe(qos.TAG_POINTS, TagPoints, self._on_points, catch_up=True)
        self.schedule = PhaseSchedule()  # which phase is solved next
        self.rest_state = None  # the registered state the tracker is built on
        self.tracker = None
        self.frame = None  # ED long-axis frame (LVFrame) of the registered model
        self.twist_span = None  # levels (0 apex, 1 base) the SA planes with ED tag points cross
        # the standard errors of the apical and basal twist gradients continued beyond the SA
        # slices at the phase of the steepest twist (where its peak is), radians per LV length
        # (twist_extrapolation_note), and that gradient
        self.twist_gradient_se, self.twist_peak_gradient = None, 0.0
        self.silence = Silence(
            TIMER_PERIOD_S
        )  # on the tag points, counted while this node is spun
        self.published = 0  # phases solved and published
        self.messages_handled = 0
        self.create_timer(TIMER_PERIOD_S, self._on_timer)
        self.report(OK, 'waiting for the registered model')

    @property
    def next_phase(self) -> int:
        """Return the phase solved next (every earlier one is solved or given up)."""
        return self.schedule.next_phase

    @property
    def num_phases(self) -> int:
        """Return the study's phases, as its tag points say (0 before any)."""
        return self.schedule.num_phases

    # ------------------------------------------------------------------ inputs
    def _build(self, model) -> None:
        if self.tracker is not None:
            return
        self.rest_state = model.state
        s, pts = model.state, model.positions
        try:
            self.tracker = MotionTracker(
                pts,
                s.translation,
                s.rotation,
                polar=model.polar,
                shape=(s.a0, s.a1, s.a2, s.a3, s.tau),
                **{k.attribute: getattr(self, k.attribute) for k in SOLVER_MODEL},
            )
        except ValueError as exc:
            self.report(ERROR, 'cannot build the model from the registration', reason=str(exc))
            self.blocked = 1  # until a registration it can build on comes
            return
        self.blocked = 0
        apex, base, ref = lv_frame_axes(pts, s.rotation)
        self.frame = LVFrame(apex, base, ref)
        self.cardiac = cardiac_coordinates(pts, self.frame)
        self.report(OK, 'model ready', particles=len(pts))
        self._advance()

    def _on_points(self, msg: TagPoints) -> None:
        self.messages_handled += 1
        if self.foreign_slice_message(msg, qos.TAG_POINTS):
            return  # another graph's tag points (nor are they input to wait on)
        self.silence.heard()
        points = self.converted(
            msg,
            conversions.msg_to_tagpoints,
            'bad tag points dropped',
            check_study=True,
            view=msg.view,
            slice=msg.slice_index,
            phase=msg.phase_index,
        )
        if points is None:
            return
        taken = self.schedule.add(points)
        said = {
            PhaseSchedule.STALE: 'tag points for an already solved phase ignored',
            PhaseSchedule.DUPLICATE: 'duplicate tag points replace the earlier set',
        }.get(taken)
        if said:
            self.report(
                WARN,
                said,
                view=points.view,
                slice=points.slice_index,
                phase=points.phase_index,
                stamp=conversions.stamp_text(msg.header.stamp),
            )
        if taken != PhaseSchedule.STALE:
            self._advance()

    def _on_timer(self) -> None:
        silent = self.silence.tick()
        if self.tracker is None or self.schedule.finished:
            return
        if self.schedule.waiting() and silent > self.incomplete_timeout_s:
            self._advance(force=True)
        elif self.subscriber_wait.waiting:
            self._advance()

    def _outputs_ready(self) -> bool:
        """
        Check whether the results may go out (a subscriber has matched).

        Outputs are VOLATILE streams, so a phase published before a subscriber has matched (e.g. by
        a solver restarted mid-run, which solves its first phases at once) never reaches it.
        """
        matched = min(
            self.motion_pub.get_subscription_count(), self.state_pub.get_subscription_count()
        )
        state = self.subscriber_wait.poll(matched)
        if state == SubscriberWait.LATE:
            self.subscriber_wait.go_on(self, matched)
        return state != SubscriberWait.WAIT

    # ------------------------------------------------------------------ solving
    def _advance(self, force: bool = False) -> None:
        """Solve every phase that is ready, in order."""
        if self.tracker is None or not self._outputs_ready():
            return
        while (ready := self.schedule.ready(force)) is not None:
            force = False
            if not ready.complete:
                self.report(
                    WARN,
                    'solving an incomplete phase',
                    phase=ready.phase,
                    slices=len(ready.sets),
                    expected=self.schedule.assembler.expected_slices,
                )
            self._solve(ready.phase, ready.sets)
            self.schedule.done(ready.phase)
            self.silence.heard()  # our own solving time is not input silence

    def _solve(self, phase: int, sets: dict) -> None:
        t0 = time.monotonic()
        tr = self.tracker
        if phase == 0:
            used = sum(tr.set_reference(pts) for pts in sets.values())
            # Only SA tags see twist: beyond the SA planes with ED points it is extrapolated.
            self.twist_span = plane_level_span(
                self.frame,
                [
                    (p.geometry.image_position, p.geometry.normal)
                    for (view, _), p in sets.items()
                    if view == TaggedFrame.VIEW_SA and len(p) and p.geometry is not None
                ],
            )
            self.report(
                OK,
                'twist measured where SA slices hold tag points',
                levels='none'
                if self.twist_span is None
                else f'{self.twist_span[0]:.2f}..{self.twist_span[1]:.2f}',
            )
            x, E = tr.rest, np.zeros((tr.num_particles, 3, 3))
            state = self.rest_state
            state.phase_index, state.num_phases, state.num_control_points = (
                0,
                self.num_phases,
                used,
            )
            state.converged = True
        else:
            try:
                sol = tr.solve(phase, sets, self.num_phases)
            except ValueError as exc:
                self.report(ERROR, 'phase not solved', phase=phase, reason=str(exc))
                return
            x, E, state = sol.positions, sol.strain, sol.state
            if tr.twist_gradient_se is not None:
                if abs(tr.twist_mean_gradient) >= self.twist_peak_gradient:
                    self.twist_peak_gradient = abs(tr.twist_mean_gradient)
                    self.twist_gradient_se = tr.twist_gradient_se
        state.study_id, state.run_id = self.study.study_id, self.study.run_id
        strain = cardiac_strain(E, self.cardiac.e_r, self.cardiac.e_c, self.cardiac.e_l)
        stamp = self.get_clock().now().to_msg()
        self.motion_pub.publish(conversions.motion_to_msg(x, tr.rest, strain, stamp))
        self.state_pub.publish(conversions.model_state_to_msg(state, stamp))
        self.published += 1
        self.report(
            OK,
            'phase solved',
            phase=phase,
            verdict=LEVEL_NAMES[state.verdict],
            control_points=state.num_control_points,
            residual_mm=round(float(state.residual), 3),
            iterations=state.iterations,
            seconds=round(time.monotonic() - t0, 3),
        )


def main(args=None):
    return run_node(MeshlessSolver, args)


if __name__ == '__main__':
    raise SystemExit(main())

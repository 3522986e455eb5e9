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
motion_analyzer: per-phase motion metrics.

``/lv/motion`` + ``/lv/model_state`` → ``/lv/metrics`` (``mlv_msgs/MotionMetrics``).

Each motion cloud is paired with the model state of identical header stamp (the solver stamps
both alike; the state carries the phase index), as message_filters' exact-time synchroniser
does. The LV frame (apex, base, circumferential reference) comes from the registered ED model;
strain is estimated by MLS from the positions (:class:`~mlv_ros.core.analysis.LVAnalyzer`).
Clouds and states are validated on arrival (finite float positions, point count of the model
once it is known; finite state, unit rotation, phase in range) and refused with a report naming
their stamp, so nothing unusable waits for a partner.

Run isolation: the node keeps to the study of the first model state it takes (``study_id``,
registered or per phase), and reports and ignores states of another study; the clouds paired
with them (same stamp: clouds cannot carry a study) are dropped with them. Metrics carry the
study.

Each metrics message also carries the per-segment findings of the cycle so far
(:class:`~mlv_ros.core.analysis.SegmentFindings`: peak and ES strain with uncertainties, the
wall-motion class) and where the AHA segments' circumferential origin came from
(``segment_origin``: the registered state's, the RV found in the images or the anatomical prior).
"""

from __future__ import annotations

from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import MotionMetrics
from mlv_ros import conversions, qos
from mlv_ros.core.analysis import LVAnalyzer, LVFrame, SegmentFindings
from mlv_ros.core.analysis.frame import lv_frame_axes
from mlv_ros.core.streaming import StampPairer
from mlv_ros.core.verdict import DEGRADED, Verdict
from mlv_ros.core.verdict import OK as OK_VERDICT
from mlv_ros.nodes.common import ERROR, GraphNode, OK, RecentKeys, run_node, stamp_key, WARN
import numpy as np
from sensor_msgs.msg import PointCloud2

_key = stamp_key
REGISTRATIONS_HELD = 4  # registered clouds / states held while waiting for their pair


class MotionAnalyzer(GraphNode):
    DIAGNOSTIC_TASK = 'motion analysis'

    def __init__(self, **node_kwargs):
        super().__init__('motion_analyzer', **node_kwargs)
        self.levels = self.param(
            'levels', 10, 'level bins apex → base', min_value=2, max_value=100
        )
        self.endo_fraction = self.param(
            'endo_fraction',
            0.2,
            'transmural depth counted as endocardium (cavity volume)',
            min_value=0.01,
            max_value=1.0,
        )
        self.max_unpaired = self.param(
            'max_unpaired',
            200,
            'motion clouds / model states held while waiting for their pair',
            min_value=1,
            max_value=100000,
        )
        self.pub = self.publisher(qos.METRICS, MotionMetrics)
        self.subscribe(qos.REGISTERED_CLOUD, PointCloud2, self._on_registered_cloud)
        self.subscribe(qos.REGISTERED_STATE, ModelStateMsg, self._on_registered_state)
        self.subscribe(qos.MOTION, PointCloud2, self._on_motion)
        self.subscribe(qos.MODEL_STATE, ModelStateMsg, self._on_state)
        self.reg_cloud = self.reg_state = self.analyzer = None
        self.findings = SegmentFindings()  # per-segment findings of the cycle so far
        self._findings_said = None  # the abnormal segments last reported
        # The registered cloud and state, paired by stamp (latched: one a registration, a few
        # restarts at most).
        self.registered = StampPairer(REGISTRATIONS_HELD)
        self._foreign_stamps = RecentKeys()  # stamps of model states of another study
        self.pairer = StampPairer(self.max_unpaired)  # motion clouds with their model states
        self.verdicts: dict = {}  # phase → (verdict level, reasons) of the latest metrics
        self.volumes: dict = {}  # phase → cavity volume, ml, of the latest metrics
        self.messages_handled = 0
        self.report(OK, 'waiting for the registered model')

    def _other_study_cloud(self, topic: str, msg) -> bool:
        """
        Check whether ``msg`` (a point cloud) is paired with a state of another study.

        Such a cloud is dropped with its state (reported on /diagnostics, counted).
        """
        key = _key(msg.header.stamp)
        if key not in self._foreign_stamps:
            return False
        self.cloud_of_other_study(
            topic, conversions.stamp_text(msg.header.stamp), self._foreign_stamps.get(key)
        )
        return True

    def _state_of_other_study(self, msg, topic: str) -> bool:
        """Whether the model state ``msg`` is of another study (reported); its cloud goes too."""
        stamp = conversions.stamp_text(msg.header.stamp)
        other = self.foreign(
            msg.study_id, topic, run_id=msg.run_id, phase=msg.phase_index, stamp=stamp
        )
        if not other:
            return False
        key = _key(msg.header.stamp)
        self._foreign_stamps.add(key, other)
        for cloud_topic, held in (
            (qos.REGISTERED_CLOUD, self.registered),
            (qos.MOTION, self.pairer),
        ):
            if 'cloud' in held.discard(key):
                self.cloud_of_other_study(cloud_topic, stamp, other)
        return True

    def _on_registered_cloud(self, msg):
        if self._other_study_cloud(qos.REGISTERED_CLOUD, msg):
            return
        try:
            cloud = conversions.msg_to_registered_cloud(msg)
        except ValueError as exc:
            self.report(
                ERROR,
                'bad registered cloud',
                stamp=conversions.stamp_text(msg.header.stamp),
                reason=str(exc),
            )
            return
        self.registered.add('cloud', _key(msg.header.stamp), cloud)
        self.registered.trim('cloud')
        self._build()

    def _on_registered_state(self, msg):
        if self._state_of_other_study(msg, qos.REGISTERED_STATE):
            return
        try:
            state = conversions.msg_to_model_state(msg)
        except ValueError as exc:
            self.report(
                ERROR,
                'bad registered state',
                stamp=conversions.stamp_text(msg.header.stamp),
                reason=str(exc),
            )
            return
        self.study.adopt(state.study_id, state.run_id)
        self.registered.add('state', _key(msg.header.stamp), state)
        self.registered.trim('state')
        self._build()

    def _build(self):
        if self.analyzer is not None:
            return
        pairs = self.registered.pairs()
        if not pairs:
            return  # the cloud or the state (same stamp) has not come yet
        _, self.reg_cloud, self.reg_state = pairs[-1]  # the latest registration complete
        model = conversions.registered_model(self.reg_cloud, self.reg_state)
        X = model.positions
        apex, base, ref = lv_frame_axes(X, self.reg_state.rotation)
        endo = None
        if model.transmural is not None:
            endo = model.transmural <= self.endo_fraction
            endo = endo if endo.sum() >= 20 else None
        try:
            self.analyzer = LVAnalyzer(
                X, LVFrame(apex, base, ref), levels=self.levels, endo_mask=endo
            )
        except ValueError as exc:
            self.report(ERROR, 'cannot analyse this model', reason=str(exc))
            self.blocked = 1  # until a registration it can build on comes
            return
        self.blocked = 0
        self.report(OK, 'analyzer ready', particles=len(X), edv_ml=round(self.analyzer.edv_ml, 1))
        self._pair()

    def _on_motion(self, msg: PointCloud2):
        self.messages_handled += 1
        stamp = conversions.stamp_text(msg.header.stamp)
        if self._other_study_cloud(qos.MOTION, msg):
            return
        try:
            x = conversions.xyz(conversions.msg_to_cloud(msg, finite=('x', 'y', 'z')))
        except ValueError as exc:
            self.report(ERROR, 'bad motion cloud dropped', stamp=stamp, reason=str(exc))
            return
        if self.analyzer is not None and x.shape[0] != self.analyzer.X.shape[0]:
            self.report(
                ERROR,
                'motion cloud does not match the registered model',
                stamp=stamp,
                points=x.shape[0],
                expected=self.analyzer.X.shape[0],
            )
            return
        self._hold('cloud', 'motion cloud', msg.header.stamp, x)

    def _on_state(self, msg: ModelStateMsg):
        self.messages_handled += 1
        if self._state_of_other_study(msg, qos.MODEL_STATE):
            return
        try:
            state = conversions.msg_to_model_state(msg)
        except ValueError as exc:
            self.report(
                ERROR,
                'bad model state dropped',
                phase=msg.phase_index,
                stamp=conversions.stamp_text(msg.header.stamp),
                reason=str(exc),
            )
            return
        self.study.adopt(state.study_id, state.run_id)
        self._hold('state', 'model state', msg.header.stamp, msg)

    @property
    def clouds(self) -> dict:
        """Return the motion clouds waiting for their model state (stamp key → positions)."""
        return self.pairer.held['cloud']

    @property
    def states(self) -> dict:
        """Return the model states waiting for their motion cloud (stamp key → message)."""
        return self.pairer.held['state']

    def _hold(self, side: str, what: str, stamp, item) -> None:
        """
        Keep ``item`` until its pair (same stamp) arrives, with bounded memory.

        The oldest goes when too many wait (e.g. states whose clouds were dropped as bad), so
        memory stays bounded, and the node says so.
        """
        self.pairer.add(side, _key(stamp), item)
        self._pair()
        for sec, nanosec in self.pairer.trim(side):
            self.report(
                WARN,
                f'unpaired {what} dropped',
                stamp=f'{sec}.{nanosec:09d}',
                held=len(self.pairer.held[side]),
            )

    def _pair(self):
        if self.analyzer is None:
            return
        for _, x, state in self.pairer.pairs():
            if x.shape[0] != self.analyzer.X.shape[0]:
                self.report(
                    ERROR,
                    'motion cloud does not match the registered model',
                    phase=state.phase_index,
                    stamp=conversions.stamp_text(state.header.stamp),
                    points=x.shape[0],
                    expected=self.analyzer.X.shape[0],
                )
                continue
            try:
                metrics = self.analyzer.phase(
                    x,
                    phase_index=state.phase_index,
                    num_phases=state.num_phases,
                    residual_mm=state.residual,
                )
                # The solver's data support first, then this phase's physiological bounds.
                verdict = Verdict.from_parts(state.verdict, state.verdict_reasons).merge(
                    Verdict.from_parts(metrics.verdict, metrics.verdict_reasons)
                )
                metrics.verdict, metrics.verdict_reasons = verdict.level, verdict.text
                metrics.study_id = state.study_id or self.study.study_id
                metrics.run_id = state.run_id or self.study.run_id
                # Where the segments' origin came from (the registered model's), and the findings
                # of the cycle so far, this phase included.
                metrics.segment_origin = self.reg_state.segment_origin
                metrics.segment_origin_confidence = self.reg_state.segment_origin_confidence
                findings = self.findings.update(metrics)
                for name, value in findings.message_fields().items():
                    setattr(metrics, name, value)
                out = conversions.metrics_to_msg(metrics, stamp=state.header.stamp)
            except ValueError as exc:
                self.report(
                    ERROR, 'metrics not computed', phase=state.phase_index, reason=str(exc)
                )
                continue
            self.pub.publish(out)
            self.published += 1
            self.verdicts[int(state.phase_index)] = (verdict.level, verdict.text)
            self.volumes[int(state.phase_index)] = float(metrics.cavity_volume_ml)
            values = {
                'phase': state.phase_index,
                'verdict': verdict.name,
                'volume_ml': round(metrics.cavity_volume_ml, 1),
                'twist_range_deg': round(
                    float(np.ptp(metrics.twist_deg)) if metrics.twist_deg.size else 0.0, 2
                ),
            }
            # A result the user must not take at face value is said so (WARN degraded, ERROR
            # failed), with why.
            level = {OK_VERDICT: OK, DEGRADED: WARN}.get(verdict.level, ERROR)
            self.report(
                level, 'metrics', **values, **({'reasons': verdict.text} if verdict.level else {})
            )
            self._say_findings(findings)

    def _say_findings(self, f) -> None:
        """
        Say which segments read akinetic / dyskinetic whenever that changes.

        The findings themselves go out in MotionMetrics.
        """
        said = (
            tuple(f.abnormal(('akinetic',))),
            tuple(f.abnormal(('dyskinetic',))),
            f.classes.count('indeterminate'),
        )
        if f.es_phase is None or said == self._findings_said:
            return
        self._findings_said = said
        self.report(
            OK,
            'regional findings',
            es_phase=f.es_phase,
            akinetic=list(said[0]) or 'none',
            dyskinetic=list(said[1]) or 'none',
            indeterminate_segments=said[2],
        )


def main(args=None):
    return run_node(MotionAnalyzer, args)


if __name__ == '__main__':
    raise SystemExit(main())

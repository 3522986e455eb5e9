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
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, stamp_key, WARN
from mlv_ros.settings import PAIRING
import numpy as np
from sensor_msgs.msg import PointCloud2


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
        self.declare_settings(PAIRING)  # self.max_unpaired
        self.pub = self.publisher(qos.METRICS, MotionMetrics)
        self.subscribe_registration(self._build)  # self.registered
        self.subscribe(qos.MOTION, PointCloud2, self._on_motion)
        self.subscribe(qos.MODEL_STATE, ModelStateMsg, self._on_state)
        self.reg_state = self.analyzer = None
        self.findings = SegmentFindings()  # per-segment findings of the cycle so far
        self._findings_said = None  # the abnormal segments last reported
        self.pairer = StampPairer(self.max_unpaired)  # motion clouds with their model states
        self.held_clouds.append((qos.MOTION, self.pairer))
        self.verdicts: dict = {}  # phase → (verdict level, reasons) of the latest metrics
        self.volumes: dict = {}  # phase → cavity volume, ml, of the latest metrics
        self.messages_handled = 0
        self.report(OK, 'waiting for the registered model')

    def _build(self, model):
        if self.analyzer is not None:
            return
        self.reg_state = model.state
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
        if self.other_study_cloud(qos.MOTION, msg):
            return
        x = self.converted(msg, _motion_positions, 'bad motion cloud dropped')
        if x is None:
            return
        if self.analyzer is not None and x.shape[0] != self.analyzer.X.shape[0]:
            self.report(
                ERROR,
                'motion cloud does not match the registered model',
                stamp=conversions.stamp_text(msg.header.stamp),
                points=x.shape[0],
                expected=self.analyzer.X.shape[0],
            )
            return
        # Held until its state comes (e.g. a state dropped as bad leaves its cloud waiting).
        key = stamp_key(msg.header.stamp)
        self.hold(self.pairer, 'cloud', key, x, self._pair, 'unpaired motion cloud dropped')

    def _on_state(self, msg: ModelStateMsg):
        self.messages_handled += 1
        if self.other_study_state(msg, qos.MODEL_STATE, phase=msg.phase_index):
            return
        state = self.converted(
            msg, conversions.msg_to_model_state, 'bad model state dropped', phase=msg.phase_index
        )
        if state is None:
            return
        self.study.adopt(state.study_id, state.run_id)
        key = stamp_key(msg.header.stamp)
        self.hold(self.pairer, 'state', key, msg, self._pair, 'unpaired model state dropped')

    @property
    def clouds(self) -> dict:
        """Return the motion clouds waiting for their model state (stamp key → positions)."""
        return self.pairer.held['cloud']

    @property
    def states(self) -> dict:
        """Return the model states waiting for their motion cloud (stamp key → message)."""
        return self.pairer.held['state']

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
                # The solver's data support first (confined to the segments of a sector it
                # names, if that is all), then this phase's physiological bounds (whole heart).
                solved = conversions.msg_to_model_state(state)
                verdict = Verdict.from_parts(
                    state.verdict, state.verdict_reasons, solved.degraded_segments
                ).merge(Verdict.from_parts(metrics.verdict, metrics.verdict_reasons))
                # The tag tracks' own regional reading (the solver's), for the findings.
                metrics.segment_tag_ecc = solved.tag_ecc
                metrics.segment_tag_ecc_unc = solved.tag_ecc_unc
                metrics.verdict, metrics.verdict_reasons = verdict.level, verdict.text
                metrics.degraded_segments = verdict.confined_to
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


def _motion_positions(msg: PointCloud2) -> np.ndarray:
    """Return a motion cloud's positions (N, 3), mm, refusing non-finite ones (ValueError)."""
    return conversions.xyz(conversions.msg_to_cloud(msg, finite=('x', 'y', 'z')))


def main(args=None):
    return run_node(MotionAnalyzer, args)


if __name__ == '__main__':
    raise SystemExit(main())

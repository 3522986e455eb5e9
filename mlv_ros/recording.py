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
Read a recorded run (RUN_DIR/run.mcap): its model, motion, metrics, report and accuracy.

What ``mlv-ros report``, ``export``, ``run`` and ``demo`` read of a recording, in one place:
:func:`check_recording` (a path that is not a run's recording, said with the fix),
:func:`read_run` (registered model, positions, model states and metrics per phase),
:func:`write_report` (the motion report), and the accuracy against a phantom's or a simulated
study's ground truth.
"""

from __future__ import annotations

from pathlib import Path


def read_run(mcap: Path) -> dict:
    """Read registered cloud/state, motion positions and metrics per phase from a recording."""
    from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
    from mlv_ros import bagio, conversions, qos
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    run = {
        'positions': {},
        'states': {},
        'metrics': {},
        'ed': None,
        'rotation': None,
        'frames': 0,
        'sa_planes': [],  # (point, normal) of every SA plane with ED tag points
        'ed_tag_sets': 0,
    }  # ED tag point sets recorded (any view, empty ones too)
    stamps = {}
    clouds = {}
    for m in bagio.read_bag(mcap, any_namespace=True):
        if m.topic == qos.REGISTERED_CLOUD:
            run['ed'] = conversions.xyz(
                conversions.msg_to_cloud(deserialize_message(m.data, PointCloud2))
            )
        elif m.topic == qos.REGISTERED_STATE:
            run['rotation'] = conversions.msg_to_model_state(
                bagio.deserialize(m.data, ModelState, m.missing)
            ).rotation
        elif m.topic == qos.MOTION:
            msg = deserialize_message(m.data, PointCloud2)
            clouds[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = conversions.xyz(
                conversions.msg_to_cloud(msg)
            )
        elif m.topic == qos.MODEL_STATE:
            msg = bagio.deserialize(m.data, ModelState, m.missing)
            stamps[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg.phase_index
            run['states'][msg.phase_index] = conversions.msg_to_model_state(msg)
        elif m.topic == qos.METRICS:
            d = conversions.msg_to_metrics(bagio.deserialize(m.data, MotionMetrics, m.missing))
            run['metrics'][d['phase_index']] = d
        elif m.topic == qos.FRAMES:
            run['frames'] += 1
        elif m.topic == qos.TAG_POINTS:
            msg = bagio.deserialize(m.data, TagPoints, m.missing)
            run['ed_tag_sets'] += msg.phase_index == 0
            if msg.view == TaggedFrame.VIEW_SA and msg.phase_index == 0 and len(msg.track_id):
                g = conversions.msg_to_geometry(msg.geometry)
                run['sa_planes'].append((g.image_position, g.normal))
    for key, x in clouds.items():
        if key in stamps:
            run['positions'][stamps[key]] = x
    return run


def phantom_accuracy(mcap: Path, preset: str, num_phases: int) -> dict:
    """Accuracy of a recorded phantom run against the preset's analytic motion."""
    from mlv_ros.core.sim import load_preset, make_motion

    run = read_run(mcap)
    if run['ed'] is None or not run['positions']:
        return {'error': 'the run has no registered model or no motion to evaluate'}
    return motion_accuracy(run, make_motion(load_preset(preset), num_phases=num_phases))


def motion_accuracy(run: dict, motion) -> dict:
    """Return the accuracy of :func:`read_run`'s ``run`` against a true motion (evaluate_run)."""
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import plane_level_span
    from mlv_ros.core.sim.evaluation import evaluate_run
    from mlv_ros.core.analysis.frame import lv_frame_axes

    frame = LVFrame(*lv_frame_axes(run['ed'], run['rotation']))
    analyzer = LVAnalyzer(run['ed'], frame)
    span = plane_level_span(frame, run.get('sa_planes') or [])
    return evaluate_run(run['ed'], run['positions'], motion, analyzer, sa_span=span)


def groundtruth_accuracy(mcap: Path, groundtruth: Path) -> dict:
    """
    Return the accuracy of a recorded run against a simulated study's ground truth.

    ``groundtruth`` is the study's ``groundtruth.json`` or its directory; the accuracy is computed
    as :func:`phantom_accuracy` does for a preset.
    """
    from mlv_ros.core.io.groundtruth import motion_from_groundtruth

    run = read_run(mcap)
    if run['ed'] is None or not run['positions']:
        return {'error': 'the run has no registered model or no motion to evaluate'}
    return motion_accuracy(run, motion_from_groundtruth(groundtruth))


def find_groundtruth(dicom_dir: Path) -> Path | None:
    """``groundtruth.json`` of a simulated study: in the DICOM directory or its parent."""
    for d in (dicom_dir, dicom_dir.parent):
        if (d / 'groundtruth.json').is_file():
            return d / 'groundtruth.json'
    return None


def check_recording(path: Path) -> None:
    """
    Raise FileNotFoundError / ValueError, with the fix, for a path that is not a run's recording.

    That is, a path missing, or holding another message type on a topic the report reads
    (deserialising it would fail deep inside rclpy).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(
            f'{path} does not exist: give RUN_DIR/run.mcap (or RUN_DIR) of a recorded run'
        )
    if path.is_dir() and not any(path.glob('*.mcap')):
        raise ValueError(
            f'{path} holds no .mcap file: give RUN_DIR/run.mcap (or RUN_DIR) of a recorded run'
        )
    if path.is_file():
        with open(path, 'rb') as fh:
            if fh.read(5) != b'\x89MCAP':
                raise ValueError(
                    f'{path} is not an MCAP file: give RUN_DIR/run.mcap (or RUN_DIR) of a '
                    'recorded run'
                )
    from mlv_ros import bagio, qos  # (after the quick checks: rclpy takes a second to import)

    try:
        topics = bagio.bag_topics(path)
    except ValueError:
        return  # no summary (a killed recorder) or not MCAP: reading it says which
    read = (
        qos.REGISTERED_CLOUD,
        qos.REGISTERED_STATE,
        qos.MOTION,
        qos.MODEL_STATE,
        qos.METRICS,
        qos.FRAMES,
        qos.TAG_POINTS,
    )  # what read_run deserialises
    graph = {
        split[1]: name for name in topics if (split := qos.split_graph_topic(name))
    }  # in any namespace
    wrong = [
        f'{graph[t]} holds {topics[graph[t]]["type"] or "an untyped channel"}, not '
        f'{qos.TOPIC_TYPES[t]}'
        for t in read
        if t in graph and topics[graph[t]]['type'] != qos.TOPIC_TYPES[t]
    ]
    if wrong:
        raise ValueError(
            f'{path} is not an mlv-ros recording: {"; ".join(wrong)} '
            '(give the run.mcap that `mlv-ros run` or `mlv-ros demo` wrote)'
        )


def load_run_data(path: Path, label: str):
    """
    Load a recording's RunData: per-phase metrics, ED and per-phase positions, LV frame.

    Check it with :func:`check_recording` first (:func:`write_report` does).
    """
    from mlv_ros.core.analysis import LVFrame, PhaseMetrics
    from mlv_ros.core.analysis.frame import plane_level_span
    from mlv_ros.core.report.summary import RunData
    from mlv_ros.core.analysis.frame import lv_frame_axes

    run = read_run(path)
    frame = None
    span = False  # not known without the model and the ED tag points
    if run['ed'] is not None and run['rotation'] is not None:
        frame = LVFrame(*lv_frame_axes(run['ed'], run['rotation']))
        if run['ed_tag_sets']:
            span = plane_level_span(frame, run['sa_planes'])
    phases = [PhaseMetrics.from_dict(d) for _, d in sorted(run['metrics'].items())]
    if frame is not None:
        phases = with_segment_uncertainty(phases, run, frame)
    return RunData(phases, run['ed'], run['positions'] or None, frame, label, span), run


def with_segment_uncertainty(phases, run: dict, frame) -> list:
    """
    Return recorded metrics with their per-segment uncertainties filled in where missing.

    MotionMetrics carries them; for recordings made before it did, they are recomputed
    here from the recorded motion exactly as the analyzer computes them (:class:`LVAnalyzer` on
    the registered ED cloud and the run's frame, MLS strain of the recorded positions, the phase's
    solver residual from ``/lv/model_state``); the recorded strains, counts and verdicts are kept.
    Phases without recorded positions keep empty uncertainties (the findings then use the
    support-only uncertainty, :meth:`SegmentFindings.update`).

    Parameters
    ----------
    phases : list of PhaseMetrics
        The recorded metrics, one per phase; those with 17 per-segment error uncertainties
        already, or without recorded positions, are returned as they are.
    run : dict
        :func:`read_run` of the recording.
    frame : LVFrame
        The run's LV frame (from the registered ED cloud and rotation), given with the ED cloud
        to :class:`LVAnalyzer`.

    """
    from dataclasses import replace

    from mlv_ros.core.analysis import LVAnalyzer
    import numpy as np

    if run.get('ed') is None or not run.get('positions'):
        return list(phases)
    try:
        an = LVAnalyzer(run['ed'], frame)
    except ValueError:
        return list(phases)
    out = []
    for p in phases:
        x = run['positions'].get(int(p.phase_index))
        if x is None or p.segment_err_unc.size == 17 or np.shape(x) != an.X.shape:
            out.append(p)
            continue
        state = run['states'].get(int(p.phase_index))
        m = an.phase(
            x,
            phase_index=p.phase_index,
            num_phases=p.num_phases,
            residual_mm=float(state.residual) if state is not None else 0.0,
        )
        out.append(
            replace(
                p,
                segment_err_unc=m.segment_err_unc,
                segment_ecc_unc=m.segment_ecc_unc,
                segment_ell_unc=m.segment_ell_unc,
            )
        )
    return out


def write_report(
    mcap: Path,
    out: Path | None = None,
    compare: Path | None = None,
    label: str | None = None,
    compare_label: str | None = None,
) -> Path:
    """
    Write the motion report of a recording (figures, summary.json, index.html); return index.html.

    Parameters
    ----------
    mcap : Path
        The recording (RUN_DIR/run.mcap or RUN_DIR).
    out : Path, optional
        Report directory (default RUN_DIR/report).
    compare : Path, optional
        A second recording shown side by side.
    label, compare_label : str, optional
        Names of the runs (default their directories' names).

    Raises
    ------
    FileNotFoundError, ValueError
        Either path is not a run's recording (:func:`check_recording`, with the fix).

    """
    for path in (mcap, compare) if compare else (mcap,):
        check_recording(path)  # a mistake in either is said before seconds of imports and reading
    from mlv_ros.core.report import build_report

    mcap = Path(mcap)
    run_dir = mcap if mcap.is_dir() else mcap.parent
    data, raw = load_run_data(mcap, label or run_dir.name)
    other = None
    if compare:
        cpath = Path(compare)
        other, _ = load_run_data(
            cpath, compare_label or (cpath if cpath.is_dir() else cpath.parent).name
        )
    missing = []
    if not data.phases:
        missing.append('no /lv/metrics in the recording')
    if data.ed_positions is None:
        missing.append('no registered model (/mlv/registered_cloud) in the recording')
    meta = {
        'title': f'LV motion — {data.label}',
        'label': data.label,
        'source': str(mcap),
        'frames_recorded': raw['frames'],
        'phases_with_metrics': len(data.phases),
        'missing': missing,
    }
    if other is not None:
        meta['compare_label'] = other.label
    return build_report(
        out or run_dir / 'report',
        data.phases,
        data.ed_positions,
        data.positions_by_phase,
        compare=other,
        meta=meta,
        frame=data.frame,
        twist_span=data.twist_span,
    )

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
``mlv-ros report RUN.mcap [--compare OTHER.mcap]``: the motion report of a recorded run.

Rebuilt from the recording alone (no tracking is recomputed): PNG figures in the spirit of the
paper's Fig. 9–16, a bull's-eye of peak strain by AHA segment, ``summary.json`` and an
``index.html`` that shows them together.
"""

from __future__ import annotations

from pathlib import Path
import sys

from mlv_ros.cli import describe_os_error, one_line
import numpy as np


def add_arguments(parser):
    parser.add_argument('mcap', help='recorded run (RUN_DIR/run.mcap or the run directory)')
    parser.add_argument(
        '--compare', help='a second recorded run shown side by side (e.g. hypertrophic)'
    )
    parser.add_argument('--out', help='report directory (default: RUN_DIR/report)')
    parser.add_argument(
        '--label', default=None, help='name of the run (default: its directory name)'
    )
    parser.add_argument('--compare-label', default=None, help='name of the comparison run')


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

    Check it with :func:`check_recording` first (:func:`build` does).
    """
    from mlv_ros.core.analysis import LVFrame, PhaseMetrics
    from mlv_ros.core.analysis.frame import plane_level_span
    from mlv_ros.core.report.summary import RunData
    from mlv_ros.core.tracking import lv_frame_axes
    from mlv_ros.tools.run import read_run

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

    MotionMetrics carries them since issue 20; for recordings made before, they are recomputed
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
        :func:`mlv_ros.tools.run.read_run` of the recording.
    frame : LVFrame
        The run's LV frame (from the registered ED cloud and rotation), given with the ED cloud
        to :class:`LVAnalyzer`.

    """
    from dataclasses import replace

    from mlv_ros.core.analysis import LVAnalyzer

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


def build(
    mcap: Path,
    out: Path | None = None,
    compare: Path | None = None,
    label: str | None = None,
    compare_label: str | None = None,
) -> Path:
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


def run(args) -> int:
    try:
        index = build(
            Path(args.mcap),
            Path(args.out) if args.out else None,
            Path(args.compare) if args.compare else None,
            args.label,
            args.compare_label,
        )
    except (FileNotFoundError, ValueError) as exc:
        print(f'mlv-ros report: {one_line(exc)}', file=sys.stderr)
        return 2
    except OSError as exc:  # mostly --out: unwritable, read-only, full
        print(
            f'mlv-ros report: cannot write the report: {describe_os_error(exc)}; '
            'choose another --out',
            file=sys.stderr,
        )
        return 2
    print(index)
    return 0

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
``mlv-ros export RUN --vtk DIR``: a recorded run as files that ParaView opens.

Files that ParaView (and any VTK or CSV tool) opens, rebuilt from the recording alone.

DIR (created; an existing one must be empty) receives:

* ``phase_NNN.vtu``: one VTK XML UnstructuredGrid of vertices per phase: the LV particles at that
  phase (mm, DICOM patient LPS) with point arrays ``displacement`` (from ED, mm), ``err``,
  ``ecc``, ``ell`` (Green–Lagrange strain relative to ED, radial / circumferential /
  longitudinal) and ``ed_position`` (mm), and field data ``phase_index``, ``num_phases``,
  ``time_fraction``, ``TimeValue`` and ``verdict`` (0 ok, 1 degraded);
* ``lv_motion.pvd``: those files as one ParaView time series (timestep = the phase's
  ``time_fraction``, else its index when the fractions do not increase);
* ``segment_strain.csv``: one row per phase with metrics × AHA segment 1–17;
* ``README.txt``: what the files hold, and which phases were left out or are degraded, and why.

A phase whose verdict is *failed* is not a measurement: it gets no ``.vtu`` and no place in the
time series, and its CSV rows carry the verdict and reasons with the strain cells empty.
Degraded phases are exported with ``verdict`` = 1 (and their reasons in the CSV and README.txt).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
import shutil
import sys
import uuid

from mlv_ros.cli import describe_os_error, one_line
from mlv_ros.core.verdict import FAILED, LEVEL_NAMES
import numpy as np

PVD_NAME, CSV_NAME, README_NAME = 'lv_motion.pvd', 'segment_strain.csv', 'README.txt'
CSV_COLUMNS = (
    'phase',
    'time_fraction',
    'segment',
    'segment_name',
    'err',
    'ecc',
    'ell',
    'particles',
    'verdict',
    'verdict_reasons',
)
NUM_SEGMENTS = 17
_POSITION, _DISPLACEMENT = ('x', 'y', 'z'), ('dx', 'dy', 'dz')


class ExportWriteError(Exception):
    """``--vtk DIR`` could not be written (the OSError is ``error``); nothing was left there."""

    def __init__(self, out: Path, error: OSError):
        self.out, self.error = out, error
        super().__init__(f'cannot write {out}: {error}')


def add_arguments(parser):
    parser.add_argument('run', metavar='RUN', help='recorded run (RUN_DIR or RUN_DIR/run.mcap)')
    parser.add_argument(
        '--vtk',
        required=True,
        metavar='DIR',
        help='directory to write the ParaView time series (.pvd + one .vtu per phase) and the '
        'per-segment strain CSV into (created; must be new or empty)',
    )


def check_out_dir(out: Path) -> None:
    """
    Raise ValueError, with the fix, when ``out`` cannot take an export.

    That is a file or a non-empty directory: an export never mixes with or overwrites other files.
    """
    if out.is_dir():
        if any(out.iterdir()):
            raise ValueError(
                f'--vtk {out} exists and is not empty: give a new directory '
                f'(e.g. {out.parent / (out.name + "-2")}) or empty this one'
            )
    elif out.exists() or out.is_symlink():
        raise ValueError(f'--vtk {out} is a file, not a directory: give a new directory')


# --------------------------------------------------------------------------- reading
def read_phases(mcap: Path) -> dict:
    """
    Read everything the export needs from a recording.

    The recording is checked with :func:`mlv_ros.recording.check_recording` first.

    Returns
    -------
    dict
        ``phases``: {phase index: {``num_phases``, ``time_fraction``, ``verdict``,
        ``verdict_reasons``, ``cloud`` (structured array of the /lv/motion fields, or None),
        ``metrics`` (the /lv/metrics dict, or None)}}; ``ed`` (N, 3) ED positions or None;
        ``unpaired``: /lv/motion clouds without a /lv/model_state of the same stamp.

    """
    from mlv_msgs.msg import ModelState
    from mlv_ros import bagio, conversions, qos
    from mlv_ros.recording import read_run
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    run = read_run(mcap)  # ED positions, model states, metrics (as the report reads them)
    # /lv/motion with every field (read_run keeps positions only), paired with its phase by the
    # stamp it shares with /lv/model_state, as read_run pairs them.
    clouds, stamp_phase = {}, {}
    for m in bagio.read_bag(mcap, topics=[qos.MOTION, qos.MODEL_STATE], any_namespace=True):
        if m.topic == qos.MOTION:
            msg = deserialize_message(m.data, PointCloud2)
            key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            try:
                clouds[key] = conversions.msg_to_cloud(msg, finite=_POSITION)
            except ValueError as exc:
                raise ValueError(
                    f'{mcap}: /lv/motion at {conversions.stamp_text(msg.header.stamp)}: {exc}'
                ) from None
        else:
            msg = bagio.deserialize(m.data, ModelState, m.missing)
            stamp_phase[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = int(msg.phase_index)
    by_phase = {stamp_phase[k]: c for k, c in clouds.items() if k in stamp_phase}

    phases = {}
    for p in sorted(set(by_phase) | set(run['metrics']) | set(run['states'])):
        state, metrics = run['states'].get(p), run['metrics'].get(p)
        if p not in by_phase and metrics is None:
            continue  # a model state alone: nothing to export
        num_phases = int(metrics['num_phases'] if metrics is not None else state.num_phases)
        levels = [(int(state.verdict), state.verdict_reasons)] if state is not None else []
        if metrics is not None:  # the analyzer's verdict already merges the solver's
            levels.append((int(metrics.get('verdict', 0)), metrics.get('verdict_reasons', '')))
        level = max((lv for lv, _ in levels), default=0)
        reasons = next((r for lv, r in reversed(levels) if lv == level), '')
        phases[p] = {
            'num_phases': num_phases,
            'time_fraction': float(metrics['time_fraction'])
            if metrics is not None
            else (p / num_phases if num_phases else 0.0),
            'verdict': level,
            'verdict_reasons': reasons,
            'cloud': by_phase.get(p),
            'metrics': metrics,
        }
    return {
        'phases': phases,
        'ed': run['ed'],
        'unpaired': sum(k not in stamp_phase for k in clouds),
    }


# --------------------------------------------------------------------------- writing
def point_arrays(cloud: np.ndarray, ed: np.ndarray | None) -> tuple[np.ndarray, dict]:
    """
    Return positions (N, 3) and the point arrays of one phase's /lv/motion cloud.

    The arrays: ``displacement`` (N, 3), every other scalar field (``err``, ``ecc``, ``ell``) as it
    was recorded, and ``ed_position`` (N, 3): the registered ED cloud when it has the same
    particles, else position − displacement.
    """
    pts = np.stack([cloud[n] for n in _POSITION], axis=-1)
    names = cloud.dtype.names
    arrays = {}
    disp = None
    if all(n in names for n in _DISPLACEMENT):
        disp = np.stack([cloud[n] for n in _DISPLACEMENT], axis=-1)
        arrays['displacement'] = disp
    for n in names:
        if n not in _POSITION and n not in _DISPLACEMENT:
            arrays[n] = np.ascontiguousarray(cloud[n])
    if ed is not None and ed.shape == pts.shape:
        arrays['ed_position'] = np.asarray(ed, dtype=np.float64)
    elif disp is not None:
        arrays['ed_position'] = pts.astype(np.float64) - disp
    return pts, arrays


def _number(value) -> str:
    return repr(float(value))


def segment_rows(phases: dict) -> list[dict]:
    """
    Return the CSV rows: every phase with metrics × AHA segment 1–17.

    Strain cells are empty where the value is no measurement: a failed phase, a segment without
    particles (``segment_count`` 0), a recording without segment strain.
    """
    from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES

    rows = []
    for p, ph in sorted(phases.items()):
        m = ph['metrics']
        if m is None:
            continue
        strain = {
            k: np.asarray(m.get(f'segment_{k}', ()), dtype=np.float64)
            for k in ('err', 'ecc', 'ell')
        }
        counts = np.asarray(m.get('segment_count', ()), dtype=np.int64)
        for s in range(NUM_SEGMENTS):
            count = int(counts[s]) if counts.size == NUM_SEGMENTS else None
            has = ph['verdict'] != FAILED and count != 0
            row = {
                'phase': p,
                'time_fraction': _number(ph['time_fraction']),
                'segment': s + 1,
                'segment_name': AHA_SEGMENT_NAMES[s],
                'particles': '' if count is None else count,
                'verdict': LEVEL_NAMES[ph['verdict']],
                'verdict_reasons': ph['verdict_reasons'],
            }
            for k, v in strain.items():
                row[k] = _number(v[s]) if has and v.size == NUM_SEGMENTS else ''
            rows.append(row)
    return rows


def _timesteps(written: list[tuple[int, dict]]) -> tuple[list[float], str]:
    fractions = [ph['time_fraction'] for _, ph in written]
    if all(np.isfinite(fractions)) and all(b > a for a, b in zip(fractions, fractions[1:])):
        return fractions, 'time_fraction (phase time / cycle duration)'
    return [
        float(p) for p, _ in written
    ], 'phase index (the recorded time fractions do not increase with the phase)'


def _readme(
    source: Path, written, timestep_kind: str, failed, degraded, no_cloud, unpaired: int
) -> str:
    lines = [
        f'LV motion exported by `mlv-ros export` from {source}',
        '',
        f'{PVD_NAME}: ParaView time series of the phase_NNN.vtu files; timestep = '
        f'{timestep_kind}.',
        'phase_NNN.vtu: VTK XML UnstructuredGrid, one vertex per LV particle.',
        '  points: position at the phase, mm, DICOM patient coordinates (LPS)',
        '  displacement: from end-diastole (phase 0), mm (3 components)',
        '  err, ecc, ell: Green-Lagrange strain E = 1/2 (F^T F - I) relative to ED, radial /',
        '    circumferential / longitudinal (negative = shortening)',
        '  ed_position: the particle at end-diastole, mm',
        '  field data: phase_index, num_phases, time_fraction, TimeValue, verdict (0 ok, 1 '
        'degraded)',
        f'{CSV_NAME}: mean strain per AHA segment (1-17) for every phase with metrics;',
        '  empty strain cells: no measurement (failed phase, or a segment without particles);',
        '  particles: particles with a strain in the segment (empty when the recording lacks '
        'counts).',
        '',
        f'Phases in the time series: {", ".join(str(p) for p, _ in written) or "none"}.',
    ]
    if failed:
        lines += [
            '',
            'Left out, verdict failed (not a measurement: never plot or report it as data):',
        ]
        lines += [f'  phase {p}: {r or "no reason recorded"}' for p, r in failed]
    if degraded:
        lines += ['', 'Degraded (exported with verdict = 1: use with care):']
        lines += [f'  phase {p}: {r or "no reason recorded"}' for p, r in degraded]
    if no_cloud:
        lines += [
            '',
            'Metrics but no /lv/motion cloud recorded (no .vtu): phases '
            f'{", ".join(map(str, no_cloud))}.',
        ]
    if unpaired:
        lines += [
            '',
            f'{unpaired} /lv/motion cloud(s) without a /lv/model_state of the same stamp were '
            'left out '
            '(their phase is unknown).',
        ]
    return '\n'.join(lines) + '\n'


def export_vtk(mcap: Path, out: Path) -> dict:
    """
    Write the export of the recording ``mcap`` into the new or empty directory ``out``.

    ``mcap`` is a run directory or its ``.mcap``. Returns a summary (the files, the phases written,
    left out and degraded).

    The files are written into a temporary directory beside ``out`` that then takes its name, so
    an export that fails leaves nothing behind.

    Raises
    ------
    FileNotFoundError, ValueError
        Not a recording of a run, nothing to export in it, or ``out`` not new or empty (the
        message says what to do).
    ExportWriteError
        ``out`` cannot be written.
    OSError
        The recording cannot be read.

    """
    from mlv_ros.core.io.vtk import write_pvd
    from mlv_ros.recording import check_recording

    mcap, out = Path(mcap), Path(out)
    check_recording(mcap)
    check_out_dir(out)
    data = read_phases(mcap)
    phases = data['phases']
    if not phases:
        raise ValueError(
            f'{mcap} holds no analysed phase (no /lv/motion paired with /lv/model_state, no '
            '/lv/metrics): '
            'nothing to export; give the run.mcap of a run that analysed its phases'
        )

    width = max(3, len(str(max(max(phases), max(ph['num_phases'] for ph in phases.values()) - 1))))
    written, failed, degraded, no_cloud = _sort_phases(phases)
    steps, step_kind = _timesteps(written)

    tmp = out.parent / f'.{out.name}.export-{uuid.uuid4().hex[:12]}'
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()  # (mode from the umask, as any directory the user makes)
    except OSError as exc:
        raise ExportWriteError(out, exc) from exc
    try:
        files = _write_phase_files(tmp, written, steps, data['ed'], width)
        write_pvd(tmp / PVD_NAME, zip(steps, files))
        with open(tmp / CSV_NAME, 'w', newline='', encoding='utf-8') as fh:
            writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
            writer.writeheader()
            writer.writerows(segment_rows(phases))
        (tmp / README_NAME).write_text(
            _readme(mcap, written, step_kind, failed, degraded, no_cloud, data['unpaired']),
            encoding='utf-8',
        )
        os.replace(tmp, out)  # (an empty directory there is replaced: rename(2))
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ExportWriteError(out, exc) from exc
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {
        'out': str(out),
        'pvd': str(out / PVD_NAME),
        'csv': str(out / CSV_NAME),
        'phases_written': [p for p, _ in written],
        'phases_failed_left_out': [p for p, _ in failed],
        'phases_degraded': [p for p, _ in degraded],
        'phases_without_cloud': no_cloud,
        'timestep': step_kind.split(' (')[0],
    }


def run(args) -> int:
    try:
        summary = export_vtk(Path(args.run), Path(args.vtk))
    except (
        ExportWriteError
    ) as exc:  # unwritable, read-only, full: said of --vtk DIR, not of a temporary name
        err = exc.error
        what = (
            describe_os_error(OSError(err.errno, err.strerror, str(exc.out)))
            if err.errno
            else one_line(err)
        )
        print(
            f'mlv-ros export: cannot write --vtk {exc.out}: {what}; choose another --vtk '
            'directory',
            file=sys.stderr,
        )
        return 2
    except (
        FileNotFoundError,
        ValueError,
    ) as exc:  # said with the fix by check_recording / check_out_dir
        print(f'mlv-ros export: {one_line(exc)}', file=sys.stderr)
        return 2
    except OSError as exc:  # the recording cannot be read
        print(f'mlv-ros export: cannot read {args.run}: {describe_os_error(exc)}', file=sys.stderr)
        return 2
    # lists on one line each: a long run's 25 phases would otherwise take a screen
    print(
        '{\n'
        + ',\n'.join(f'  {json.dumps(k)}: {json.dumps(v)}' for k, v in summary.items())
        + '\n}'
    )
    return 0


def _sort_phases(phases: dict) -> tuple[list, list, list, list]:
    """
    Sort the recorded phases by what the export does with them, each in phase order.

    Returns
    -------
    written : list of (int, dict)
        Phases with a cloud, not failed.
    failed, degraded : list of (int, list)
        Phases failed (left out) and degraded, with their verdict reasons.
    no_cloud : list of int
        Phases not failed but without a cloud (left out).

    """
    written = [
        (p, ph)
        for p, ph in sorted(phases.items())
        if ph['cloud'] is not None and ph['verdict'] != FAILED
    ]
    failed = [
        (p, ph['verdict_reasons']) for p, ph in sorted(phases.items()) if ph['verdict'] == FAILED
    ]
    degraded = [
        (p, ph['verdict_reasons']) for p, ph in sorted(phases.items()) if ph['verdict'] == 1
    ]
    no_cloud = [
        p for p, ph in sorted(phases.items()) if ph['cloud'] is None and ph['verdict'] != FAILED
    ]
    return written, failed, degraded, no_cloud


def _write_phase_files(tmp: Path, written: list, steps, ed, width: int) -> list[str]:
    """
    Write one ``.vtu`` of points per phase written; return their names.

    Parameters
    ----------
    tmp : Path
        The directory written into.
    written : list of (int, dict)
        The phases (:func:`_sort_phases`).
    steps : sequence of float
        Each phase's TimeValue (:func:`_timesteps`).
    ed : np.ndarray or None
        The registered ED cloud (:func:`point_arrays`).
    width : int
        Digits of the phase number in the file names.

    Returns
    -------
    list of str

    """
    from mlv_ros.core.io.vtk import write_vtu_points

    files = []
    for (p, ph), t in zip(written, steps):
        pts, arrays = point_arrays(ph['cloud'], ed)
        name = f'phase_{p:0{width}d}.vtu'
        write_vtu_points(
            tmp / name,
            pts,
            arrays,
            {
                'phase_index': np.int32(p),
                'num_phases': np.int32(ph['num_phases']),
                'time_fraction': np.float64(ph['time_fraction']),
                'TimeValue': np.float64(t),
                'verdict': np.int32(ph['verdict']),
            },
        )
        files.append(name)
    return files

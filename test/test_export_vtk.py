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
``mlv-ros export RUN --vtk DIR`` read back with independent readers, and its refusals.

``mlv-ros export RUN --vtk DIR``: a small recording written with BagWriter (4 phases of 300
particles with known displacements and strains: ok, degraded, failed, ok) is exported and read
back with independent readers: every ``.vtu`` with meshio, the ``.pvd`` with ElementTree, the CSV
with the csv module. Also the one-line refusals (missing path, not a recording, DIR not empty).
"""

from __future__ import annotations

import csv
from pathlib import Path
import xml.etree.ElementTree as ET

import meshio
from mlv_ros import bagio, cli, conversions, qos
from mlv_ros.core.types import ModelState
from mlv_ros.tools import export
import numpy as np
import pytest
from rclpy.serialization import serialize_message

N, PHASES = 300, 4
VERDICTS = {0: (0, ''), 1: (1, 'few tag points'), 2: (2, 'no SA slice'), 3: (0, '')}
T0 = 1_700_000_000_000_000_000


def _run_data(seed: int = 7):
    rng = np.random.default_rng(seed)
    ed = rng.normal(0.0, 20.0, size=(N, 3))
    phases = {}
    for p in range(PHASES):
        d = (0.0 if p == 0 else 1.0) * rng.normal(0.0, 2.0, size=(N, 3))
        strain = (0.0 if p == 0 else 1.0) * rng.normal(0.0, 0.1, size=(N, 3))
        phases[p] = {'x': ed + d, 'd': d, 'strain': strain}
    return ed, phases


def _metrics(p: int) -> dict:
    level, reasons = VERDICTS[p]
    counts = np.full(17, 10, dtype=np.int64)
    counts[16] = 0 if p == 3 else 10  # an empty apex segment: its strain is no measurement
    seg = np.arange(1, 18) * 0.001 * (p + 1)
    return {
        'phase_index': p,
        'num_phases': PHASES,
        'time_fraction': p / PHASES,
        **{k: np.zeros(0) for k in conversions.METRIC_LEVEL_FIELDS},
        'la_radius_mm': 40.0,
        'torsion_deg_per_cm': 1.0,
        'cavity_volume_ml': 100.0,
        'ejection_fraction': 0.1 * p,
        'segment_err': seg,
        'segment_ecc': -seg,
        'segment_ell': -0.5 * seg,
        'segment_count': counts,
        'level_count': np.zeros(0, dtype=np.int64),
        'verdict': level,
        'verdict_reasons': reasons,
    }


def write_recording(run_dir: Path):
    """
    Write run.mcap as the recorder writes it.

    run.mcap as the recorder writes it: registered ED cloud/state, then per phase /lv/motion
    and /lv/model_state (one stamp) and /lv/metrics.
    """
    ed, phases = _run_data()
    w = bagio.BagWriter(run_dir / 'run.mcap')
    for topic in (
        qos.REGISTERED_CLOUD,
        qos.REGISTERED_STATE,
        qos.MOTION,
        qos.MODEL_STATE,
        qos.METRICS,
    ):
        w.add_topic(topic, qos.TOPIC_TYPES[topic], [qos.qos_dict(qos.topic_qos(topic))])
    t = T0
    stamp = 1.0
    ed_cloud = {'x': ed[:, 0], 'y': ed[:, 1], 'z': ed[:, 2]}
    w.write(
        qos.REGISTERED_CLOUD,
        serialize_message(
            conversions.cloud_to_msg(
                conversions.structured(ed_cloud, np.float64), conversions.make_header(stamp)
            )
        ),
        t,
    )
    w.write(
        qos.REGISTERED_STATE,
        serialize_message(
            conversions.model_state_to_msg(ModelState(num_phases=PHASES, num_particles=N), stamp)
        ),
        t + 1,
    )
    for p, ph in phases.items():
        t, stamp = t + 1_000_000, stamp + 0.1
        x, d, e = ph['x'], ph['d'], ph['strain']
        cloud = {
            'x': x[:, 0],
            'y': x[:, 1],
            'z': x[:, 2],
            'dx': d[:, 0],
            'dy': d[:, 1],
            'dz': d[:, 2],
            'err': e[:, 0],
            'ecc': e[:, 1],
            'ell': e[:, 2],
        }
        level, reasons = VERDICTS[p]
        w.write(
            qos.MOTION,
            serialize_message(
                conversions.cloud_to_msg(
                    conversions.structured(cloud), conversions.make_header(stamp)
                )
            ),
            t,
        )
        w.write(
            qos.MODEL_STATE,
            serialize_message(
                conversions.model_state_to_msg(
                    ModelState(
                        phase_index=p,
                        num_phases=PHASES,
                        num_particles=N,
                        verdict=level,
                        verdict_reasons=reasons,
                    ),
                    stamp,
                )
            ),
            t + 1,
        )
        w.write(
            qos.METRICS, serialize_message(conversions.metrics_to_msg(_metrics(p), stamp)), t + 2
        )
    w.close()
    return ed, phases


@pytest.fixture(scope='module')
def exported(tmp_path_factory):
    base = tmp_path_factory.mktemp('export')
    ed, phases = write_recording(base / 'run')
    out = base / 'vtk'
    assert cli.main(['export', str(base / 'run'), '--vtk', str(out)]) == 0
    return out, ed, phases


def test_pvd_is_a_time_series_of_the_phases_that_are_measurements(exported):
    out, _, _ = exported
    root = ET.parse(out / export.PVD_NAME).getroot()
    assert root.tag == 'VTKFile' and root.get('type') == 'Collection'
    sets = root.find('Collection').findall('DataSet')
    steps = [float(s.get('timestep')) for s in sets]
    assert steps == [0.0, 0.25, 0.75]  # time fractions, in order; phase 2 (failed) left out
    assert [s.get('file') for s in sets] == ['phase_000.vtu', 'phase_001.vtu', 'phase_003.vtu']
    assert all((out / s.get('file')).is_file() for s in sets)
    assert not (out / 'phase_002.vtu').exists()
    readme = (out / export.README_NAME).read_text()
    assert 'phase 2: no SA slice' in readme and 'phase 1: few tag points' in readme


def test_every_vtu_reads_back_with_meshio(exported):
    out, ed, phases = exported
    for p in (0, 1, 3):
        mesh = meshio.read(out / f'phase_{p:03d}.vtu')
        x, d, e = phases[p]['x'], phases[p]['d'], phases[p]['strain']
        assert mesh.points.shape == (N, 3)
        np.testing.assert_array_equal(mesh.points, x.astype(np.float32))
        np.testing.assert_allclose(mesh.point_data['displacement'], d, rtol=0, atol=1e-5)
        for i, name in enumerate(('err', 'ecc', 'ell')):
            np.testing.assert_array_equal(mesh.point_data[name], e[:, i].astype(np.float32))
        np.testing.assert_array_equal(mesh.point_data['ed_position'], ed)
        assert [c.type for c in mesh.cells] == ['vertex'] and len(mesh.cells[0].data) == N
        assert int(mesh.field_data['phase_index'][0]) == p
        assert int(mesh.field_data['verdict'][0]) == VERDICTS[p][0]  # degraded phase 1 flagged
        assert float(mesh.field_data['time_fraction'][0]) == p / PHASES


def test_segment_csv_has_every_phase_and_segment(exported):
    out, _, _ = exported
    with open(out / export.CSV_NAME, newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == PHASES * 17
    assert [(int(r['phase']), int(r['segment'])) for r in rows] == [
        (p, s) for p in range(PHASES) for s in range(1, 18)
    ]
    by = {(int(r['phase']), int(r['segment'])): r for r in rows}
    r = by[(1, 5)]
    assert (float(r['err']), float(r['ecc']), float(r['ell'])) == (
        0.005 * 2,
        -0.005 * 2,
        -0.0025 * 2,
    )
    assert (
        r['particles'] == '10'
        and r['verdict'] == 'degraded'
        and r['verdict_reasons'] == 'few tag points'
    )
    assert float(r['time_fraction']) == 0.25 and r['segment_name'] == 'basal inferolateral'
    failed = [by[(2, s)] for s in range(1, 18)]
    assert all(f['verdict'] == 'failed' and f['err'] == f['ecc'] == f['ell'] == '' for f in failed)
    assert by[(3, 17)]['particles'] == '0' and by[(3, 17)]['ecc'] == ''  # no particles: no value
    assert by[(3, 16)]['ecc'] != ''


def _refusal(args, capsys) -> str:
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('mlv-ros export: ') and 'Traceback' not in err
    return err


def test_refusals_are_one_line_with_the_fix(exported, tmp_path, capsys):
    out, _, _ = exported
    run = out.parent / 'run'
    err = _refusal(['export', str(tmp_path / 'nope'), '--vtk', str(tmp_path / 'a')], capsys)
    assert 'does not exist' in err and 'give RUN_DIR' in err
    (tmp_path / 'notes.mcap').write_text('not a recording')
    err = _refusal(['export', str(tmp_path / 'notes.mcap'), '--vtk', str(tmp_path / 'a')], capsys)
    assert 'not an MCAP file' in err
    err = _refusal(['export', str(run), '--vtk', str(out)], capsys)
    assert 'exists and is not empty' in err and 'give a new directory' in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['notes.mcap']  # nothing written
    # a recording without analysed phases (frames only)
    w = bagio.BagWriter(tmp_path / 'frames' / 'run.mcap')
    w.add_topic(qos.FRAMES, qos.TOPIC_TYPES[qos.FRAMES], [qos.qos_dict(qos.topic_qos(qos.FRAMES))])
    w.close()
    err = _refusal(['export', str(tmp_path / 'frames'), '--vtk', str(tmp_path / 'b')], capsys)
    assert 'nothing to export' in err and not (tmp_path / 'b').exists()
    # an existing empty directory is taken
    (tmp_path / 'empty').mkdir()
    assert cli.main(['export', str(run), '--vtk', str(tmp_path / 'empty')]) == 0
    assert (tmp_path / 'empty' / export.PVD_NAME).is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.')]  # no temporary left

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
Single-line tag studies through the real DICOM path and the whole graph, against the truth.

``mlv-ros simulate --protocol`` with ``tag_lines: pair`` writes two single-line series of every
slice (the second with its lines turned by 90°, as vendors acquire them in two breath-holds,
here in one place: the angle and shift fixed, not drawn; other angles and shifts:
``test_tags_line_pair``, ``test_tracking_lines``);
``mlv-ros run --dicom`` pairs them into one slice with both families, and the tag detector
tracks points on each family's lines along their normals. The same study's first series alone
is a one-family study: only motion across its lines is measured, and every phase says so
(degraded). A small study (128² at 1.8 mm, 7 mm lines, 6 SA + 2 LA, 14 phases) keeps it short;
the pair runs with the default 3000 particles (with 1000 its ES median is 1.05 mm, over the
bound), the one-family study, whose verdict alone is checked, with 1000.
"""

import json
from pathlib import Path
import subprocess
import sys

from mlv_ros.recording import groundtruth_accuracy
from mlv_ros.runner import run_graph
import pytest

pytestmark = pytest.mark.slow  # graph runs: scheduled first (conftest)

BIN = Path(sys.executable).parent
# The legacy apex cap (apex_thickening null): this test is about pairing single-line series;
# with a thickening cap drawn the ES twist error is 2.48° here (docs/benchmarks.md, cap20).
PROTOCOL = """\
tag_lines: pair
line_pair_angle_deg: 90.0
line_pair_shift_mm: [0.0, 0.0]
line_pair_through_mm: 0.0
abnormal_regions: []
apex_thickening: null
right_ventricle: false
shape: normal
size: 128
pixel_spacing_mm: 1.8
tag_spacing_mm: 7.0
sa_slices: 6
la_planes: 2
num_phases: 14
snr: 25.0
"""


@pytest.fixture(scope='module')
def line_study(tmp_path_factory):
    root = tmp_path_factory.mktemp('single_line_graph')
    (root / 'pair.yaml').write_text(PROTOCOL)
    study = root / 'study'
    subprocess.run(
        [
            str(BIN / 'mlv-ros'), 'simulate', '--random', '41', '--protocol',
            str(root / 'pair.yaml'), '--out', str(study), '--no-progress',
        ],
        check=True,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return root, study


def _run(root: Path, dicom: Path, name: str, particles: int | None = None) -> dict:
    return run_graph(
        {'source': 'dicom', 'path': str(dicom)},
        root / name,
        overrides={'registration': {'num_particles': particles}} if particles else None,
        timeout=400,
        progress=lambda *_: None,
    )


def test_two_single_line_series_are_paired_and_solved(line_study):
    """
    Check the paired study: every phase solved and ok, ES accuracy within issue 14's bounds.

    Both families of every slice were tracked (no phase flags single-line data), and the ES
    displacement matches the analytic truth: median ≤ 1.0 mm, p95 ≤ 2.5 mm, twist ≤ 2° (the
    grid studies' must; measured 0.66 / 1.36 mm, 1.08°), every phase's median ≤ 1.0 mm.
    """
    root, study = line_study
    summary = _run(root, study / 'dicom', 'pair')
    assert summary['complete'] and summary['phases_solved'] == summary['num_phases'] == 14
    assert not summary['phases_failed'], summary['phases_failed']
    assert '8 of 8 slice(s) paired' in summary['dicom_study'], summary['dicom_study']
    assert 'single-line' not in json.dumps(summary['phases_degraded']), summary['phases_degraded']
    acc = groundtruth_accuracy(Path(summary['mcap']), study)
    es = acc['es']
    assert es['median_mm'] <= 1.0 and es['p95_mm'] <= 2.5, json.dumps(es)
    assert es['twist_error_deg'] <= 2.0, json.dumps(es)
    assert max(r['median_mm'] for r in acc['per_phase']) <= 1.0


def test_one_family_of_lines_is_read_and_marked_degraded(line_study):
    """
    Check a one-family study (the first series alone): solved, and no phase after ED is ok.

    Every solved phase after ED carries the 1-D verdict (motion measured only across the lines).
    """
    root, study = line_study
    summary = _run(root, study / 'dicom' / 'lines_1', 'single', particles=1000)
    assert summary['complete'] and summary['phases_solved'] == summary['num_phases'] == 14
    assert '0 of 8 slice(s) paired' in summary['dicom_study'], summary['dicom_study']
    degraded = summary['phases_degraded']
    assert sorted(int(p) for p in degraded) == list(range(1, 14)), degraded
    assert all(
        'single-line tags on 8 of 8 slices' in why and 'only across the tag lines' in why
        for why in degraded.values()
    ), degraded

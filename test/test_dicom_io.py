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

"""DICOM write → read round trip, SA/LA classification from geometry, ground truth files, CLI."""

import json
import shutil

from mlv_ros.core.io import (
    estimate_long_axis,
    load_groundtruth,
    read_dicom_dir,
    write_groundtruth,
    write_study_dicom,
)
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import VIEW_SA
import numpy as np
import pydicom
import pytest


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20.0, size=64, num_phases=4, subplanes=1, seed=1)


@pytest.fixture(scope='module')
def written(study, tmp_path_factory):
    d = tmp_path_factory.mktemp('dicom')
    return d, write_study_dicom(study, d)


def test_files_carry_required_attributes(study, written):
    _, paths = written
    assert len(paths) == len(study.frames) == 44
    ds = pydicom.dcmread(paths[0])
    fr = study.frames[0]
    assert ds.Modality == 'MR'
    assert ds.SOPClassUID == pydicom.uid.MRImageStorage
    assert ds.SeriesInstanceUID == fr.series_uid
    assert ds.SeriesDescription.startswith('tagged SA')
    assert (ds.Rows, ds.Columns) == fr.image.shape
    assert ds.BitsAllocated == 16 and ds.PixelRepresentation == 0
    assert ds.pixel_array.dtype == np.uint16
    assert ds.CardiacNumberOfImages == 4 and ds.InstanceNumber == 1
    assert float(ds.TriggerTime) == pytest.approx(fr.trigger_time * 1000.0)
    np.testing.assert_allclose(
        [float(v) for v in ds.ImagePositionPatient], fr.geometry.image_position, atol=1e-4
    )
    np.testing.assert_allclose(
        [float(v) for v in ds.PixelSpacing], [fr.geometry.row_spacing, fr.geometry.column_spacing]
    )
    assert float(ds.SliceThickness) == pytest.approx(fr.geometry.slice_thickness)
    series = {pydicom.dcmread(p, stop_before_pixels=True).SeriesInstanceUID for p in paths}
    assert len(series) == 11  # one series per slice location


def test_round_trip_pixels_and_geometry(study, written):
    d, paths = written
    frames, problems = read_dicom_dir(d)
    assert problems == []
    assert len(frames) == len(study.frames)
    got = {(f.view, f.slice_index, f.phase_index): f for f in frames}
    for f in study.frames:
        r = got[(f.view, f.slice_index, f.phase_index)]
        # stored uint16 = round(1000 · intensity), read back with RescaleSlope 0.001
        np.testing.assert_allclose(r.image, f.image, atol=0.5e-3 + 1e-6)
        np.testing.assert_allclose(r.geometry.image_position, f.geometry.image_position, atol=1e-4)
        np.testing.assert_allclose(r.geometry.row_direction, f.geometry.row_direction, atol=1e-5)
        np.testing.assert_allclose(
            r.geometry.column_direction, f.geometry.column_direction, atol=1e-5
        )
        assert r.geometry.row_spacing == pytest.approx(f.geometry.row_spacing)
        assert r.geometry.slice_thickness == pytest.approx(f.geometry.slice_thickness)
        assert r.trigger_time == pytest.approx(f.trigger_time, abs=1e-6)
        assert r.cycle_duration == pytest.approx(f.cycle_duration)
        assert r.num_phases == f.num_phases and r.series_uid == f.series_uid
    # raw stored pixels identical to what was written
    ds = pydicom.dcmread(paths[5])
    expect = np.rint(study.frames[5].image.astype(np.float64) * 1000).astype(np.uint16)
    np.testing.assert_array_equal(ds.pixel_array, expect)


def test_classification_with_shuffled_renamed_files(study, written, tmp_path):
    d, paths = written
    rng = np.random.default_rng(7)
    flat = tmp_path / 'scrambled'
    (flat / 'a' / 'b').mkdir(parents=True)
    for i, j in enumerate(rng.permutation(len(paths))):
        sub = flat if i % 3 else flat / 'a' / 'b'
        shutil.copy(paths[j], sub / f'x{rng.integers(1 << 30):09d}')
    res = read_dicom_dir(flat)
    assert res.problems == []
    assert len(res.series) == 11
    truth = {study.series_uids[k]: k for k in study.keys}
    for s in res.series:  # same view and index as simulated, found from geometry alone
        assert (s.view, s.slice_index) == truth[s.series_uid]
        assert len(s.files) == 4
    for f in res.frames:  # phases ordered by trigger time
        assert f.trigger_time == pytest.approx(study.motion.times[f.phase_index], abs=1e-6)
    ax = res.long_axis
    fr = study.motion.frame
    assert ax.source == 'la_planes'
    np.testing.assert_allclose(ax.direction, fr.long_axis, atol=1e-5)
    # the estimated point lies on the true axis
    v = ax.point - fr.apex
    assert np.linalg.norm(v - (v @ fr.long_axis) * fr.long_axis) < 1e-3


def test_classification_ignores_descriptions(study, written, tmp_path):
    d, paths = written
    for i, p in enumerate(paths):
        ds = pydicom.dcmread(p)
        ds.SeriesDescription = 'cine'
        ds.SeriesNumber = 1
        ds.save_as(tmp_path / f'f{i}')
    res = read_dicom_dir(tmp_path)
    views = {s.series_uid: s.view for s in res.series}
    assert sum(v == VIEW_SA for v in views.values()) == 8
    for k in study.keys:
        assert views[study.series_uids[k]] == k[0]


def test_long_axis_from_sa_only(study):
    sa = [study.geometries[(VIEW_SA, i)] for i in range(8)]
    centres = np.array([g.pixel_to_patient(np.array([31.5, 31.5])) for g in sa])
    ax = estimate_long_axis(sa, [], centres)
    assert ax.source == 'sa_normal'
    np.testing.assert_allclose(ax.direction, study.motion.frame.long_axis, atol=1e-9)
    assert estimate_long_axis([], []) is None


def test_groundtruth_round_trip(study, tmp_path):
    write_groundtruth(study, tmp_path, n_points=300)
    gt = load_groundtruth(tmp_path)
    m = study.motion
    assert gt.trajectories.shape == (4, 300, 3)
    np.testing.assert_allclose(gt.trajectories[2], m.position(gt.material_points, 2), atol=1e-4)
    assert m.inside_myocardium(gt.material_points).all()
    for k in study.keys:
        np.testing.assert_array_equal(gt.ed_masks[k], study.ed_masks[k])
        np.testing.assert_allclose(
            gt.geometries[k].image_position, study.geometries[k].image_position
        )
    assert gt.curves['twist_deg'].shape == (4, 21)
    assert gt.meta['preset']['name'] == 'normal'
    meta = json.loads((tmp_path / 'groundtruth.json').read_text())
    meta['format'] = 'other'
    (tmp_path / 'groundtruth.json').write_text(json.dumps(meta))
    with pytest.raises(ValueError, match='not a mlv_ros.groundtruth'):
        load_groundtruth(tmp_path)


def test_simulate_cli(tmp_path):
    from mlv_ros.cli import main

    rc = main(
        [
            'simulate',
            '--preset',
            'cylinder',
            '--out',
            str(tmp_path),
            '--size',
            '48',
            '--phases',
            '3',
            '--subplanes',
            '1',
            '--points',
            '50',
            '--no-progress',
        ]
    )
    assert rc == 0
    res = read_dicom_dir(tmp_path / 'dicom')
    assert len(res.frames) == 33 and res.problems == []
    assert load_groundtruth(tmp_path).meta['preset']['name'] == 'cylinder'
    assert main(['simulate', '--preset', 'nope', '--out', str(tmp_path / 'x')]) == 2

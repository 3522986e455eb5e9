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

"""The DICOM reader on damaged directories: every bad file is reported, the rest still loads."""

from pathlib import Path
import shutil

from mlv_ros.core.io import DicomReadError, read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import VIEW_LA
import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
import pytest


@pytest.fixture(scope='module')
def good(tmp_path_factory):
    s = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=2)
    d = tmp_path_factory.mktemp('good')
    return s, write_study_dicom(s, d)


def _copy_all(paths, dest: Path) -> list[Path]:
    dest.mkdir(parents=True, exist_ok=True)
    out = []
    for i, p in enumerate(paths):
        q = dest / f'img{i:03d}'
        shutil.copy(p, q)
        out.append(q)
    return out


def test_bad_files_reported_rest_loads(good, tmp_path):
    study, paths = good
    d = tmp_path / 'study'
    files = _copy_all(paths, d)
    # 1. corrupt: random bytes
    (d / 'corrupt.dcm').write_bytes(np.random.default_rng(0).bytes(3000))
    # 2. truncated copy of a valid image (its original still loads)
    raw = files[0].read_bytes()
    (d / 'truncated.dcm').write_bytes(raw[:len(raw) * 2 // 3])
    (d / 'header_cut.dcm').write_bytes(raw[:1000])  # cut inside the header, before the pixels
    # 3. non-image DICOM (no PixelData)
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = '1.2.840.10008.5.1.4.1.1.88.11'  # Basic Text SR
    meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
    meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
    sr = Dataset()
    sr.file_meta = meta
    sr.SOPClassUID = meta.MediaStorageSOPClassUID
    sr.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    sr.Modality = 'SR'
    sr.save_as(d / 'report.dcm', enforce_file_format=True)
    # 4. a whole series (LA 2) without ImagePositionPatient
    la2 = study.series_uids[(VIEW_LA, 2)]
    missing = []
    for f in files:
        ds = pydicom.dcmread(f)
        if ds.SeriesInstanceUID == la2:
            del ds.ImagePositionPatient
            ds.save_as(f)
            missing.append(str(f))
    # 5. one image of SA 1 replaced by a smaller one (same series and plane)
    sa1 = study.series_uids[(0, 1)]
    odd = next(
        f
        for f in files
        if pydicom.dcmread(f, stop_before_pixels=True).SeriesInstanceUID == sa1
        and pydicom.dcmread(f, stop_before_pixels=True).InstanceNumber == 2
    )
    ds = pydicom.dcmread(odd)
    ds.Rows, ds.Columns = 32, 32
    ds.PixelData = np.zeros((32, 32), np.uint16).tobytes()
    ds.save_as(odd)

    res = read_dicom_dir(d)
    why = dict(res.problems)
    assert 'not a DICOM file' in why[str(d / 'corrupt.dcm')]
    assert 'pixel data unreadable' in why[str(d / 'truncated.dcm')]
    assert 'truncated' in why[str(d / 'header_cut.dcm')]
    assert 'no pixel data' in why[str(d / 'report.dcm')]
    assert len(missing) == 3
    for f in missing:
        assert why[f] == 'missing geometry tag(s): ImagePositionPatient'
    assert 'image size 32x32 differs' in why[str(odd)]
    assert len(res.problems) == 4 + 3 + 1
    # everything valid still loads: 10 series; SA 1 has 2 phases left
    assert len(res.series) == 10
    assert sum(s.view == VIEW_LA for s in res.series) == 2
    n_sa1 = [len(s.files) for s in res.series if s.series_uid == sa1]
    assert n_sa1 == [2]
    assert len(res.frames) == 33 - 3 - 1


def test_empty_directory_is_a_clear_error(tmp_path):
    with pytest.raises(DicomReadError, match='no files under'):
        read_dicom_dir(tmp_path)
    with pytest.raises(FileNotFoundError, match='DICOM directory not found'):
        read_dicom_dir(tmp_path / 'missing')


def test_only_junk_is_a_clear_error(tmp_path):
    (tmp_path / 'a.txt').write_text('hello')
    with pytest.raises(DicomReadError, match='no usable DICOM image') as err:
        read_dicom_dir(tmp_path)
    assert err.value.problems[0][0] == str(tmp_path / 'a.txt')


def test_missing_trigger_time_falls_back_to_instance_number(good, tmp_path):
    study, paths = good
    sa0 = study.series_uids[(0, 0)]
    for i, p in enumerate(paths):
        ds = pydicom.dcmread(p)
        if ds.SeriesInstanceUID != sa0:
            continue
        del ds.TriggerTime
        ds.save_as(tmp_path / f'z{9 - i}')
    res = read_dicom_dir(tmp_path)
    inst = [
        int(pydicom.dcmread(f, stop_before_pixels=True).InstanceNumber)
        for f in res.series[0].files
    ]
    assert inst == [1, 2, 3]
    np.testing.assert_allclose([f.trigger_time for f in res.frames], study.motion.times, atol=1e-9)

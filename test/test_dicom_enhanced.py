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
Enhanced MR multi-frame input.

Enhanced MR multi-frame input: a simulated study converted at test time
(``corpus/enhanced.py`` writes the functional groups) loads frame for frame as its classic files
do, one file per cine, per stack, per frame, or as a Legacy Converted Enhanced MR; damaged
functional groups are reported per file; and a full run on it analyses
the study with what was left out and not used in its summary.
"""

import json
from pathlib import Path
import shutil
import subprocess
import sys
from types import SimpleNamespace

from corpus.enhanced import convert_study
from mlv_ros.core.io import DicomReadError, read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import VIEW_SA
from mlv_ros.nodes.frame_source import read_bag_frames
import numpy as np
import pydicom
from pydicom.data import get_testdata_file
import pytest

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

BIN = Path(sys.executable).parent


def _place(fr):
    """
    Return a frame's identity independent of series UIDs and file names.

    A frame's identity independent of series UIDs and file names (and, for long-axis views,
    of their order, which goes by SeriesNumber first: one per stack in a per-stack file).
    """
    g = fr.geometry
    return (
        fr.view,
        fr.slice_index if fr.view == VIEW_SA else -1,
        fr.phase_index,
        tuple(np.round(g.image_position, 4)),
        tuple(np.round(g.normal, 4)),
    )


def _assert_same_frames(got, want, same_series: bool) -> None:
    """Pixels (dtype and values), geometry, indices and timing identical, frame for frame."""
    want_of = {_place(f): f for f in want}
    assert sorted(want_of) == sorted(_place(f) for f in got)
    for fr in got:
        w = want_of[_place(fr)]
        assert fr.image.dtype == w.image.dtype and np.array_equal(fr.image, w.image)
        assert (fr.num_phases, fr.trigger_time, fr.cycle_duration) == (
            w.num_phases,
            w.trigger_time,
            w.cycle_duration,
        )
        for name in (
            'image_position',
            'row_direction',
            'column_direction',
            'row_spacing',
            'column_spacing',
            'slice_thickness',
        ):
            assert np.array_equal(getattr(fr.geometry, name), getattr(w.geometry, name)), name
        assert not same_series or fr.series_uid == w.series_uid


@pytest.fixture(scope='module')
def study(tmp_path_factory):
    root = tmp_path_factory.mktemp('enhanced')
    sim = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=3)
    paths = write_study_dicom(sim, root / 'classic')
    return SimpleNamespace(root=root, sim=sim, paths=paths, ref=read_dicom_dir(root / 'classic'))


@pytest.mark.parametrize(
    'per,legacy',
    [('cine', False), ('stack', False), ('frame', False), ('stack', True)],
    ids=['per_cine', 'per_stack', 'per_frame', 'legacy_per_stack'],
)
def test_enhanced_mr_loads_as_the_classic_files(study, per, legacy):
    out = study.root / f'{per}_{legacy}'
    files = convert_study(study.paths, out, per=per, legacy=legacy)
    assert len(files) == {'cine': 11, 'stack': 2, 'frame': 33}[per]
    assert pydicom.dcmread(files[0], stop_before_pixels=True).SOPClassUID == (
        '1.2.840.10008.5.1.4.1.1.4.4' if legacy else '1.2.840.10008.5.1.4.1.1.4.1'
    )
    res = read_dicom_dir(out)
    # (At 48² one cine of this study fails the tag test: used, with the same warning as classic.)
    assert res.problems == [] and res.complete

    def tag_test(warnings):
        return sorted(w.split('its ED image')[1].split('; used')[0] for _, w in warnings)

    assert len(study.ref.warnings) == 1 and tag_test(res.warnings) == tag_test(study.ref.warnings)
    assert res.study_uid == study.ref.study_uid and len(res.series) == 11
    _assert_same_frames(res.frames, study.ref.frames, same_series=per != 'stack')
    assert np.allclose(res.long_axis.direction, study.ref.long_axis.direction)


def test_legacy_converted_enhanced_mr_written_by_highdicom(study, tmp_path):
    """
    Check the reader against an independent Enhanced writer (highdicom): the same frames.

    An independent Enhanced writer: highdicom's LegacyConvertedEnhancedMRImage of each classic
    series (one file per cine, functional groups as highdicom lays them out): the same frames.
    """
    from highdicom.legacy import LegacyConvertedEnhancedMRImage
    from pydicom.uid import generate_uid

    series: dict[str, list] = {}
    for p in study.paths:
        ds = pydicom.dcmread(p)
        series.setdefault(ds.SeriesInstanceUID, []).append(ds)
    for k, (uid, datasets) in enumerate(sorted(series.items())):
        enhanced = LegacyConvertedEnhancedMRImage(
            legacy_datasets=datasets,
            series_instance_uid=generate_uid(entropy_srcs=['highdicom', uid]),
            series_number=int(datasets[0].SeriesNumber),
            sop_instance_uid=generate_uid(entropy_srcs=['sop', uid]),
            instance_number=k + 1,
        )
        enhanced.save_as(tmp_path / f'lce_{k:02d}.dcm', enforce_file_format=True)
    first = pydicom.dcmread(tmp_path / 'lce_00.dcm', stop_before_pixels=True)
    assert first.SOPClassUID == '1.2.840.10008.5.1.4.1.1.4.4' and int(first.NumberOfFrames) == 3
    res = read_dicom_dir(tmp_path)
    assert res.problems == [] and res.complete and len(res.series) == 11
    _assert_same_frames(res.frames, study.ref.frames, same_series=False)


def test_enhanced_mr_beside_classic_files_and_damaged_functional_groups(study, tmp_path):
    """
    Check Enhanced files of the study beside foreign files: the study read, bad files reported.

    Enhanced files of the study beside foreign files (CT_small, an Enhanced copy of SA 2 with
    its frames' positions cut): the study, as its classic files; each bad file reported once.
    """
    convert_study(study.paths, tmp_path / 'study', per='cine')
    shutil.copy(get_testdata_file('CT_small.dcm', download=False), tmp_path)
    sa2 = [p for p in study.paths if p.parent.name == 'SA_02']
    bad = convert_study(sa2, tmp_path / 'bad', per='stack')[0]
    ds = pydicom.dcmread(bad)
    del ds.PerFrameFunctionalGroupsSequence[1].PlanePositionSequence
    ds.save_as(bad, enforce_file_format=True)
    short = convert_study(sa2, tmp_path / 'short', per='stack')[0]
    ds = pydicom.dcmread(short)
    del ds.PerFrameFunctionalGroupsSequence[2]
    ds.save_as(short, enforce_file_format=True)
    res = read_dicom_dir(tmp_path)
    _assert_same_frames(res.frames, study.ref.frames, same_series=True)
    why = dict(res.problems)
    assert sorted(why) == sorted(map(str, [bad, short, tmp_path / 'CT_small.dcm']))
    assert 'frame 2 of 3: missing geometry tag(s): ImagePositionPatient' in why[str(bad)]
    assert 'PerFrameFunctionalGroupsSequence has 2 item(s) for NumberOfFrames 3' in why[str(short)]
    assert 'modality CT' in why[str(tmp_path / 'CT_small.dcm')]
    with pytest.raises(DicomReadError, match='frame 2 of 3'):
        read_dicom_dir(tmp_path / 'bad')


def test_run_on_enhanced_mr_with_a_study_chosen_and_parts_left_out(tmp_path):
    """
    Check a full ``mlv-ros run`` on an Enhanced MR study.

    A full ``mlv-ros run``: a study as Enhanced MR (one file per cine) in a
    folder with CT_small, and one of its cines acquired with 2 phases of 3 (left out), chosen with
    --study. Every phase is analysed from exactly the classic files' frames, but the run is not
    complete (exit 1): summary.json says what was left out and what was not used.
    """
    sim = simulate_study('normal', snr=20.0, size=128, num_phases=3, subplanes=1, seed=1)
    classic = write_study_dicom(sim, tmp_path / 'classic')
    folder = tmp_path / 'folder'
    sa5 = [p for p in classic if p.parent.name == 'SA_05']
    convert_study([p for p in classic if p not in sa5], folder, per='cine')
    two = [pydicom.dcmread(p) for p in sa5[:2]]
    for k, ds in enumerate(two):
        ds.CardiacNumberOfImages, ds.TriggerTime = 2, 500.0 * k
        ds.save_as(folder / f'sa5_{k}.dcm', enforce_file_format=True)
    shutil.copy(get_testdata_file('CT_small.dcm', download=False), folder)
    done = subprocess.run(
        [
            str(BIN / 'mlv-ros'),
            'run',
            '--dicom',
            str(folder),
            '--study',
            sim.study_uid,
            '--out',
            str(tmp_path / 'run'),
            '--particles',
            '200',
            '--quiet',
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    summary = json.loads((tmp_path / 'run' / 'summary.json').read_text())
    assert done.returncode == 1, done.stderr[-2000:]
    assert summary['phases_complete'] and summary['metrics_published'] == 3
    assert summary['complete'] is False and summary['input_complete'] is False
    assert sim.study_uid in summary['dicom_study'] and 'asked for' in summary['dicom_study']
    (left,) = summary['left_out']
    assert (
        left.startswith(str(folder / 'sa5_0.dcm'))
        and '2 phase(s)' in left
        and 'the study has 3' in left
    )
    assert [n.split(':')[0] for n in summary['not_used']] == [
        str(folder / 'CT_small.dcm'),
        str(folder / 'sa5_0.dcm'),
    ]
    said = [
        line
        for line in done.stderr.splitlines()
        if line.startswith('mlv-ros run: incomplete input')
    ]
    assert len(said) == 1 and 'see left_out in summary.json' in said[0], done.stderr[-2000:]
    # The console: a short summary on stdout (what was run, the part left out, the exit status),
    # no INFO lines of the nodes (without --verbose) and no progress bar (no terminal).
    shown = done.stdout.splitlines()
    assert len(shown) <= 30 and shown[0].startswith(
        f'run: dicom {folder} (study {sim.study_uid})'
    ), done.stdout
    assert 'input: 1 part(s) of the study left out' in done.stdout and shown[-1].startswith(
        'exit 1: not complete'
    )
    assert '3 of 3 phases solved, 3 analysed' in done.stdout and 'volumes: ED ' in done.stdout, (
        done.stdout
    )
    assert '[INFO]' not in done.stderr and 'phases analysed' not in done.stderr, done.stderr[
        -2000:
    ]
    # The frames recorded are the classic files' own, SA 5 excepted.
    ref = read_dicom_dir(tmp_path / 'classic')
    sa5_uid = sim.series_uids[(VIEW_SA, 5)]
    recorded = read_bag_frames(str(tmp_path / 'run' / 'run.mcap'))
    want = {(f.series_uid, f.phase_index): f for f in ref.frames if f.series_uid != sa5_uid}
    assert len(recorded) == len(want) == 30
    for fr in recorded:
        w = want[(fr.series_uid, fr.phase_index)]
        assert np.array_equal(fr.image, w.image) and fr.trigger_time == w.trigger_time
        assert np.array_equal(fr.geometry.image_position, w.geometry.image_position)

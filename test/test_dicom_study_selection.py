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
Study selection in the DICOM reader: the tagged study out of a messy folder.

Real files written at test time: small simulated tagged studies (``write_study_dicom``), pydicom's
bundled ``CT_small.dcm`` / ``MR_small.dcm`` (``get_testdata_file(..., download=False)``: never a
download) made into series of their own, and edited copies of the study's cines (an untagged one,
a repeat of a slice, cines with other phase counts).
"""

import copy
from pathlib import Path
import shutil
from types import SimpleNamespace

from corpus.dicom_cases import frames_by_path
from mlv_ros.core.io import dicom as dicom_io
from mlv_ros.core.io import DicomReadError, read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import load_preset, simulate_study
from mlv_ros.core.types import TAGS_LINE_PAIR, TAGS_LINES, VIEW_SA
import numpy as np
import pydicom
from pydicom.data import get_testdata_file
from pydicom.uid import generate_uid
import pytest


def _key(fr):
    return fr.series_uid, fr.view, fr.slice_index, fr.phase_index


def _same_frames(res, ref) -> None:
    """``res`` holds exactly ``ref``'s frames, pixels and geometry bit-identical."""
    want = {_key(f): f for f in ref.frames}
    assert sorted(map(_key, res.frames)) == sorted(want)
    for fr in res.frames:
        w = want[_key(fr)]
        assert fr.image.dtype == w.image.dtype and np.array_equal(fr.image, w.image)
        assert (fr.num_phases, fr.trigger_time, fr.cycle_duration) == (
            w.num_phases,
            w.trigger_time,
            w.cycle_duration,
        )
        for name in ('image_position', 'row_direction', 'column_direction'):
            assert np.array_equal(getattr(fr.geometry, name), getattr(w.geometry, name))


def _cine(paths: list[Path], folder: str) -> list[pydicom.Dataset]:
    """Return the datasets of one written series (files under ``folder``), in phase order."""
    return [pydicom.dcmread(p) for p in paths if p.parent.name == folder]


def _save_series(datasets, out: Path, name: str, **tags) -> list[Path]:
    """Save ``datasets`` as a new series (new Series/SOP UIDs) with ``tags`` set, under ``out``."""
    uid = generate_uid(entropy_srcs=['series', name])
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for k, src in enumerate(datasets):
        ds = copy.deepcopy(src)
        ds.SeriesInstanceUID = uid
        ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = generate_uid(
            entropy_srcs=[name, str(k)]
        )
        for tag, value in tags.items():
            setattr(ds, tag, value(ds, k) if callable(value) else value)
        written.append(out / f'{name}_{k:03d}.dcm')
        ds.save_as(written[-1], enforce_file_format=True)
    return written


def _foreign(
    out: Path, untagged_paths: list[Path], study_uid: str, for_uid: str
) -> dict[str, list[Path]]:
    """
    Write series that must not be used under ``out``.

    Series that must not be used, written under ``out``: a 12-slice × 3-phase CT of another
    study, MR_small.dcm, an untagged MR cine of another study, and an untagged cine of the tagged
    study itself (as a cine SSFP beside the tagged slices; from ``untagged_paths``, a study
    simulated without tags).
    """
    series = {}
    ct = pydicom.dcmread(get_testdata_file('CT_small.dcm', download=False))
    ct_uid, ct_for = generate_uid(entropy_srcs=['ct study']), generate_uid(entropy_srcs=['ct for'])
    images = [ct] * 36
    series['ct'] = _save_series(
        images,
        out,
        'ct',
        StudyInstanceUID=ct_uid,
        FrameOfReferenceUID=ct_for,
        ImagePositionPatient=lambda ds, k: [0.0, 0.0, 5.0 * (k // 3)],
        TriggerTime=lambda ds, k: 100.0 * (k % 3),
        CardiacNumberOfImages=3,
    )
    mr = pydicom.dcmread(get_testdata_file('MR_small.dcm', download=False))
    series['mr_small'] = _save_series([mr], out, 'mr_small')
    series['mr_other_study'] = _save_series(
        _cine(untagged_paths, 'SA_02'), out, 'mr_other', SeriesNumber=30
    )
    series['untagged'] = _save_series(
        _cine(untagged_paths, 'SA_03'),
        out,
        'untagged',
        SeriesNumber=31,
        StudyInstanceUID=study_uid,
        FrameOfReferenceUID=for_uid,
    )
    return series


@pytest.fixture(scope='module')
def studies(tmp_path_factory):
    root = tmp_path_factory.mktemp('study_selection')
    a = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=2)
    b = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=5)
    a_paths = write_study_dicom(a, root / 'a')
    b_paths = [
        p
        for p in write_study_dicom(b, root / 'b')
        if p.parent.name in ('SA_01', 'SA_03', 'SA_05', 'LA_00')
    ]
    for d in (root / 'b').iterdir():  # study B: 4 of its 11 cines
        if d.name not in ('SA_01', 'SA_03', 'SA_05', 'LA_00'):
            shutil.rmtree(d)
    plain = load_preset('normal')
    plain['imaging']['tag_spacing_mm'] = 1e6  # no tags: a cine SSFP of the same anatomy
    untagged = write_study_dicom(
        simulate_study(plain, snr=20.0, size=48, num_phases=3, subplanes=1, seed=4),
        root / 'untagged',
    )
    myo = load_preset('normal')
    myo['imaging']['background_m0'] = 0.0  # tags on the heart alone: no cine passes the tag test
    myo_study = simulate_study(myo, snr=20.0, size=48, num_phases=3, subplanes=1, seed=6)
    write_study_dicom(myo_study, root / 'myo')
    ref_a, ref_b = read_dicom_dir(root / 'a'), read_dicom_dir(root / 'b')
    assert ref_a.study_uid == a.study_uid and ref_b.study_uid == b.study_uid != a.study_uid
    assert (
        len(ref_a.frames) == 33 and len(ref_b.frames) == 12 and ref_a.complete and ref_b.complete
    )
    return SimpleNamespace(
        root=root,
        a=a,
        b=b,
        a_paths=a_paths,
        b_paths=b_paths,
        ref_a=ref_a,
        ref_b=ref_b,
        untagged=untagged,
        myo=myo_study,
        ref_myo=read_dicom_dir(root / 'myo'),
    )


def _shuffle_flat(root: Path, seed: int) -> dict[Path, Path]:
    """Every .dcm under ``root`` moved into ``root/flat`` under random names; old → new path."""
    files = sorted(root.rglob('*.dcm'))
    flat = root / 'flat'
    flat.mkdir()
    moved = {}
    for p, n in zip(files, np.random.default_rng(seed).permutation(len(files))):
        moved[p] = flat / f'{n:04d}'
        shutil.move(p, moved[p])
    return moved


def test_tag_band_is_the_detectors():
    from mlv_ros.core.tags.gabor import TAG_PERIOD_RANGE_MM

    assert dicom_io._TAG_PERIOD_MM == TAG_PERIOD_RANGE_MM


@pytest.mark.parametrize(
    'order', ['foreign_first', 'foreign_last', 'shuffled', 'shuffled_myocardium_only']
)
def test_mixed_folder_gives_the_tagged_study_whatever_the_file_order(studies, order, tmp_path):
    """
    Check that foreign and untagged series beside the tagged study are listed, not used.

    A CT series, MR_small, an untagged MR cine of another study and an untagged cine of the
    study itself beside the tagged study: the tagged study, bit-identical to it read alone, and
    each foreign series listed once with its reason. Also with tags on the heart alone (a study
    of 48² images: 7 of its 11 cines pass the clear tag test).
    """
    which = 'myo' if order.endswith('myocardium_only') else 'a'
    study, ref = getattr(studies, which), getattr(studies, f'ref_{which}')
    first, last = ('0_', '9_') if order == 'foreign_first' else ('9_', '0_')
    foreign = _foreign(
        tmp_path / f'{first}foreign',
        studies.untagged,
        study.study_uid,
        study.frame_of_reference_uid,
    )
    shutil.copytree(studies.root / which, tmp_path / f'{last}study')
    root = tmp_path
    if order.startswith('shuffled'):  # everything flat under random names, interleaved
        moved = _shuffle_flat(tmp_path, 3)
        foreign = {k: [moved[p] for p in v] for k, v in foreign.items()}
        root = tmp_path / 'flat'
    res = read_dicom_dir(root)
    assert res.study_uid == study.study_uid and study.study_uid in res.choice
    assert next(iter(res.studies)) == study.study_uid and 'tagged cine' in res.choice
    _same_frames(res, ref)
    assert res.complete and res.left_out == [] and res.warnings == []
    why = dict(res.problems)
    first = {name: min(map(str, files)) for name, files in foreign.items()}
    assert sorted(why) == sorted(first.values())  # each series once, by its first file
    expect = {
        'ct': ['modality CT', 'another study', '12 planes', '36 image(s)'],
        'mr_small': ['one frame', 'another study'],
        'mr_other_study': ['another study'],
        'untagged': ['not tagged'],
    }
    for name, parts in expect.items():
        reason = why[first[name]]
        assert 'not used' in reason and all(p in reason for p in parts), (name, reason)
    assert 'another study' not in why[first['untagged']]


def test_the_study_with_more_tagged_cines_and_the_study_argument(studies, tmp_path):
    shutil.copytree(studies.root / 'a', tmp_path / 'a')
    shutil.copytree(studies.root / 'b', tmp_path / 'b')
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == studies.a.study_uid
    assert list(res.studies) == [studies.a.study_uid, studies.b.study_uid]
    assert res.studies[studies.a.study_uid] > res.studies[studies.b.study_uid] > 0
    assert studies.b.study_uid in res.choice  # the other study is named
    _same_frames(res, studies.ref_a)
    why = dict(res.problems)
    assert len(why) == 4 and all('another study' in r for r in why.values())
    # study= picks the other one: its frames as read alone, study A's 11 series listed.
    res = read_dicom_dir(tmp_path, study=studies.b.study_uid)
    assert res.study_uid == studies.b.study_uid and 'asked for' in res.choice
    _same_frames(res, studies.ref_b)
    assert len(res.problems) == 11 and all('another study' in r for _, r in res.problems)
    assert res.complete
    with pytest.raises(
        DicomReadError, match=f'study 1.2.3.4 is not under .*{studies.a.study_uid}'
    ):
        read_dicom_dir(tmp_path, study='1.2.3.4')
    # Whatever the file order: both studies interleaved under random names.
    for seed in (11, 12):
        moved = _shuffle_flat(tmp_path, seed)
        res = read_dicom_dir(tmp_path / 'flat')
        assert res.study_uid == studies.a.study_uid and len(res.not_used) == 4 and res.complete
        _same_frames(res, studies.ref_a)
        for old, new in moved.items():
            shutil.move(new, old)
        (tmp_path / 'flat').rmdir()


def test_a_repeated_slice_keeps_the_later_acquisition(studies, tmp_path):
    """
    Check that a slice acquired again is used from its later series, the earlier one listed.

    SA 3 acquired again (another series, another noise draw): the later one is used in its
    place, the earlier listed, and a warning says so; by SeriesNumber, or by SeriesTime where
    the times tell (here against the numbers).
    """
    other = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=9)
    redo = write_study_dicom(other, tmp_path / 'redo_src')
    sa3 = _cine(redo, 'SA_03')
    uid, for_uid = studies.a.study_uid, studies.a.frame_of_reference_uid
    original = studies.a.series_uids[(VIEW_SA, 3)]
    for case, tags, later in (
        ('by_number', {'SeriesNumber': 20}, 'repeat'),
        ('by_time', {'SeriesNumber': 2, 'SeriesTime': '101500'}, 'repeat'),
        ('earlier_by_time', {'SeriesNumber': 20, 'SeriesTime': '094500'}, 'original'),
    ):
        folder = tmp_path / case
        shutil.copytree(studies.root / 'a', folder / 'study')
        if 'SeriesTime' in tags:  # the original series acquired at 10:00
            for p in (folder / 'study').rglob('*.dcm'):
                ds = pydicom.dcmread(p)
                ds.SeriesDate, ds.SeriesTime = '20240105', '100000'
                ds.save_as(p, enforce_file_format=True)
            tags = {**tags, 'SeriesDate': '20240105'}
        files = _save_series(
            sa3,
            folder / 'repeat',
            'repeat',
            StudyInstanceUID=uid,
            FrameOfReferenceUID=for_uid,
            **tags,
        )
        res = read_dicom_dir(folder)
        assert res.study_uid == uid and len(res.series) == 11, case
        assert sum(s.view == VIEW_SA for s in res.series) == 8, case
        why = dict(res.problems)
        assert len(why) == 1 and 'repeated acquisition' in next(iter(why.values())), (case, why)
        assert len(res.warnings) == 1 and 'acquired more than once' in res.warnings[0][1], case
        assert res.complete, case
        used = {s.series_uid for s in res.series}
        repeat_uid = pydicom.dcmread(files[0], stop_before_pixels=True).SeriesInstanceUID
        if later == 'repeat':
            assert repeat_uid in used and original not in used, case
            assert next(iter(why)) == str(folder / 'study' / 'SA_03' / 'IM_0001.dcm'), case
            got, alone = frames_by_path(res), frames_by_path(read_dicom_dir(folder / 'repeat'))
            assert all(np.array_equal(got[str(f)].image, alone[str(f)].image) for f in files), case
        else:
            assert original in used and repeat_uid not in used, case
            assert next(iter(why)) == str(files[0]), case
            _same_frames(res, studies.ref_a)


def test_cines_with_other_phase_counts(studies, tmp_path):
    """
    Check cines with fewer or more phases than the study.

    A cine with fewer phases than the study is left out with its reason (complete false); one
    with more is matched to the study's phases by nearest trigger time.
    """
    uid, for_uid = studies.a.study_uid, studies.a.frame_of_reference_uid
    shutil.copytree(studies.root / 'a', tmp_path / 'study')
    # SA 5 acquired with 2 phases (its own CardiacNumberOfImages): too few.
    shutil.rmtree(tmp_path / 'study' / 'SA_05')
    two = _cine(studies.a_paths, 'SA_05')[:2]
    short = _save_series(
        two,
        tmp_path / 'study' / 'SA_05',
        'two_phases',
        CardiacNumberOfImages=2,
        TriggerTime=lambda ds, k: 500.0 * k,
        NominalInterval=1000,
    )
    # SA 6 acquired with 5 phases (0, 200, ..., 800 ms against the study's 0, 333, 667).
    five_sim = simulate_study('normal', snr=20.0, size=48, num_phases=5, subplanes=1, seed=2)
    five_src = write_study_dicom(five_sim, tmp_path / 'five_src')
    shutil.rmtree(tmp_path / 'study' / 'SA_06')
    five = _save_series(
        _cine(five_src, 'SA_06'),
        tmp_path / 'study' / 'SA_06',
        'five_phases',
        StudyInstanceUID=uid,
        FrameOfReferenceUID=for_uid,
    )
    res = read_dicom_dir(tmp_path / 'study')
    assert res.study_uid == uid and not res.complete
    assert len(res.left_out) == 1 and res.left_out[0][0] == str(short[0])
    assert '2 phase(s)' in res.left_out[0][1] and 'the study has 3' in res.left_out[0][1]
    why = dict(res.problems)
    assert list(why) == [str(short[0])] and 'too few' in why[str(short[0])]
    assert len(res.series) == 10 and sum(s.view == VIEW_SA for s in res.series) == 7
    # The 5-phase cine: its images at 0, 400, 600 ms (nearest 0, 333, 667), as phases 0, 1, 2 of 3.
    got = frames_by_path(res)
    used = [f for f in five if str(f) in got]
    assert used == [five[0], five[2], five[3]]
    assert [got[str(f)].phase_index for f in used] == [0, 1, 2]
    assert all(got[str(f)].num_phases == 3 for f in used)
    assert [round(got[str(f)].trigger_time, 3) for f in used] == [0.0, 0.4, 0.6]
    alone = read_dicom_dir(tmp_path / 'study' / 'SA_06')  # the same pixels as the cine read alone
    assert all(
        np.array_equal(got[str(f)].image, frames_by_path(alone)[str(f)].image) for f in used
    )
    assert len(res.warnings) == 1 and '5 phases in a study of 3' in res.warnings[0][1]
    # Every other frame as in the study read alone.
    ref = frames_by_path(studies.ref_a)
    others = {p: fr for p, fr in got.items() if Path(p).parent.name not in ('SA_05', 'SA_06')}
    assert len(others) == 27
    for p, fr in others.items():
        want = ref[str(studies.root / 'a' / Path(p).relative_to(tmp_path / 'study'))]
        assert np.array_equal(fr.image, want.image) and fr.phase_index == want.phase_index


def test_frame_source_takes_the_study_parameter(studies, tmp_path, ros_context):
    from mlv_ros.nodes.frame_source import FrameSource
    from rclpy.parameter import Parameter

    shutil.copytree(studies.root / 'a', tmp_path / 'a')
    shutil.copytree(studies.root / 'b', tmp_path / 'b')
    nodes = []
    try:
        for study, want, frames in (
            ('', studies.a.study_uid, 33),
            (studies.b.study_uid, studies.b.study_uid, 12),
        ):
            node = FrameSource(
                context=ros_context,
                parameter_overrides=[
                    Parameter('source', value='dicom'),
                    Parameter('path', value=str(tmp_path)),
                    Parameter('study', value=study),
                    Parameter('exit_when_done', value=False),
                ],
            )
            nodes.append(node)
            assert node.study_id == want and len(node.frames) == frames and node.input_complete
            assert want in node.dicom_choice
            assert all(f.study_id == want for f in node.frames)
            said = [values for message, values in node._reports if message == 'DICOM study chosen']
            assert len(said) == 1 and want in said[0]['choice']
    finally:
        for node in nodes:
            node.destroy_node()


def test_an_unreadable_file_of_the_study_makes_it_incomplete(studies, tmp_path):
    shutil.copytree(studies.root / 'a', tmp_path / 'a')
    bad = tmp_path / 'a' / 'LA_02' / 'IM_0002.dcm'
    ds = pydicom.dcmread(bad)
    del ds.ImagePositionPatient
    ds.save_as(bad, enforce_file_format=True)
    (tmp_path / 'a' / 'notes.txt').write_text('not DICOM')
    # A presentation state of the study (no pixels): reported, but nothing of the study is missing.
    gsps = pydicom.dcmread(bad, stop_before_pixels=True)
    gsps.SOPClassUID = gsps.file_meta.MediaStorageSOPClassUID = '1.2.840.10008.5.1.4.1.1.11.1'
    gsps.SOPInstanceUID = gsps.file_meta.MediaStorageSOPInstanceUID = generate_uid(
        entropy_srcs=['gsps']
    )
    gsps.Modality = 'PR'
    for tag in (
        'Rows',
        'Columns',
        'BitsAllocated',
        'BitsStored',
        'HighBit',
        'PixelRepresentation',
        'SamplesPerPixel',
        'PhotometricInterpretation',
    ):
        delattr(gsps, tag)
    gsps.save_as(tmp_path / 'a' / 'gsps.dcm', enforce_file_format=True)
    res = read_dicom_dir(tmp_path)
    assert not res.complete and len(res.frames) == 32
    left, cine = dict(res.left_out), str(tmp_path / 'a' / 'LA_02' / 'IM_0001.dcm')
    assert sorted(left) == [cine, str(bad)]  # the file, and its cine (kept, missing phase 2)
    assert 'not read' in left[str(bad)] and 'missing geometry' in left[str(bad)]
    assert 'phase(s) 2 of 3 missing' in left[cine]
    assert [p for p, _ in res.warnings] == [cine]
    assert sorted(p for p, _ in res.problems) == [
        str(bad),
        str(tmp_path / 'a' / 'gsps.dcm'),
        str(tmp_path / 'a' / 'notes.txt'),
    ]
    assert 'non-image DICOM' in dict(res.problems)[str(tmp_path / 'a' / 'gsps.dcm')]


def test_another_frame_of_reference_and_a_folder_without_tags(studies, tmp_path):
    # SA 7 of the study in another frame of reference (the patient moved, a new localizer): not
    # used, and the study is incomplete.
    shutil.copytree(studies.root / 'a', tmp_path / 'a')
    moved = sorted((tmp_path / 'a' / 'SA_07').glob('*.dcm'))
    for p in moved:
        ds = pydicom.dcmread(p)
        ds.FrameOfReferenceUID = generate_uid(entropy_srcs=['moved'])
        ds.save_as(p, enforce_file_format=True)
    res = read_dicom_dir(tmp_path / 'a')
    assert res.study_uid == studies.a.study_uid and len(res.series) == 10 and not res.complete
    assert [p for p, _ in res.left_out] == [p for p, _ in res.problems] == [str(moved[0])]
    assert 'another frame of reference of the chosen study' in res.problems[0][1]
    # No tagged cine anywhere: the study with the most MR cines, all of them; MR_small not used.
    plain = tmp_path / 'plain'
    shutil.copytree(studies.untagged[0].parent.parent, plain / 'study')
    shutil.copy(get_testdata_file('MR_small.dcm', download=False), plain)
    res = read_dicom_dir(plain)
    assert len(res.frames) == 33 and res.complete and 'no cine shows a tag grid' in res.choice
    assert [p for p, _ in res.problems] == [str(plain / 'MR_small.dcm')]


def test_cines_of_the_study_that_fail_the_tag_test(studies, tmp_path):
    """
    Check which of the study's untagged cines are used.

    The study's untagged cines: one acquired later at a tagged slice's place is not used (the
    tagged one is; no repeat); one at a place of its own, acquired like the tagged cines, is used
    with a warning (a failed tag test never costs a slice of the study's kind); one acquired
    otherwise (another pixel size) is not used.
    """
    uid, for_uid = studies.a.study_uid, studies.a.frame_of_reference_uid
    shutil.copytree(studies.root / 'a', tmp_path / 'study')
    sa3 = _cine(studies.untagged, 'SA_03')
    later = _save_series(
        sa3,
        tmp_path / 'later',
        'later',
        StudyInstanceUID=uid,
        FrameOfReferenceUID=for_uid,
        SeriesNumber=40,
        SeriesDate='20990101',
        SeriesTime='235959',
    )
    normal = studies.a.geometries[(VIEW_SA, 3)].normal
    half = 0.5 * abs(
        float(
            (
                studies.a.geometries[(VIEW_SA, 4)].image_position
                - studies.a.geometries[(VIEW_SA, 3)].image_position
            )
            @ normal
        )
    )
    between = _save_series(
        sa3,
        tmp_path / 'between',
        'between',
        StudyInstanceUID=uid,
        FrameOfReferenceUID=for_uid,
        SeriesNumber=41,
        ImagePositionPatient=lambda ds, k: [
            float(v) for v in np.asarray(ds.ImagePositionPatient, float) + half * normal
        ],
    )
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == uid and res.complete
    why = dict(res.problems)
    assert list(why) == [str(later[0])]
    assert (
        'not tagged' in why[str(later[0])]
        and 'at this slice position is used' in why[str(later[0])]
    )
    assert studies.a.series_uids[(VIEW_SA, 3)] in {s.series_uid for s in res.series}
    ((path, warning),) = res.warnings
    assert path == str(between[0]) and 'shows no clear tag grid' in warning and 'used' in warning
    assert sum(s.view == VIEW_SA for s in res.series) == 9 and len(res.frames) == 36
    # The same cine with 1.25 x the pixel size: acquired unlike the tagged cines, not used.
    shutil.rmtree(tmp_path / 'later')
    for p in between:
        ds = pydicom.dcmread(p)
        ds.PixelSpacing = [float(v) * 1.25 for v in ds.PixelSpacing]
        ds.save_as(p, enforce_file_format=True)
    res = read_dicom_dir(tmp_path)
    assert res.complete and res.warnings == [] and list(dict(res.problems)) == [str(between[0])]
    assert (
        'not tagged' in res.problems[0][1]
        and "acquired unlike the study's tagged cines" in res.problems[0][1]
    )
    _same_frames(res, studies.ref_a)


#: A study tagged on the heart alone: dark surroundings, 128² px of 1.8 mm.
HEART_ONLY = {
    'shape': 'normal',
    'background': 'none',
    'size': 128,
    'pixel_spacing_mm': 1.8,
    'snr': 20.0,
    'tag_spacing_mm': 7.0,
    'tag_angle_deg': 30.0,
    'num_phases': 3,
    'sa_slices': 6,
    'la_planes': 2,
}


@pytest.fixture(scope='module')
def heart_only(tmp_path_factory):
    """
    Write a heart-only tagged study and an untagged bright-blood study of the same protocol.

    A study tagged on the heart alone (dark surroundings, 128² px of 1.8 mm: no cine passes the
    whole-image tag test) and an untagged bright-blood study of the same protocol with more
    cines (9 SA + 2 LA against 6 + 2), both written by ``write_study_dicom``.
    """
    from mlv_ros.core.sim.protocol import protocol_preset

    root = tmp_path_factory.mktemp('heart_only')
    preset = protocol_preset(HEART_ONLY)
    kw = {'snr': 20.0, 'size': 128, 'num_phases': 3, 'subplanes': 1, 'pixel_spacing': 1.8}
    tagged = simulate_study(preset, seed=21, **kw)
    preset['imaging'].update(tag_spacing_mm=1e6, blood_m0=2.0, sa_slices=9)
    untagged = simulate_study(preset, seed=22, **kw)
    assert tagged.study_uid != untagged.study_uid
    write_study_dicom(tagged, root / 'tagged')
    write_study_dicom(untagged, root / 'untagged')
    return SimpleNamespace(
        root=root, tagged=tagged, untagged=untagged, ref=read_dicom_dir(root / 'tagged')
    )


def test_tags_on_the_heart_alone_are_found_by_the_study_vote(heart_only):
    """
    Check the heart-only study's cines against the whole-image and windowed tag tests.

    No cine of the heart-only study passes the whole-image test; its cines share a grid at the
    protocol's period in windows, the untagged twin's do not.
    """
    ed = {
        name: [f.image for f in getattr(heart_only, name).frames if f.phase_index == 0]
        for name in ('tagged', 'untagged')
    }
    assert max(dicom_io._tag_grid(im, 1.8)[0] for im in ed['tagged']) < dicom_io._TAG_CLEAR
    vote = dicom_io._study_vote([([im], 1.8) for im in ed['tagged']])
    assert vote.grid >= dicom_io._TAG_STUDY and abs(vote.period_mm / 7.0 - 1.0) <= 0.06
    assert not vote.single_line
    assert dicom_io._study_vote([([im], 1.8) for im in ed['untagged']]).score < 1.0
    res = heart_only.ref
    assert res.study_uid == heart_only.tagged.study_uid and 'tags on the heart alone' in res.choice
    assert len(res.frames) == 24 and res.complete


@pytest.mark.parametrize('order', ['tagged_first', 'untagged_first', 'shuffled'])
def test_a_larger_untagged_study_does_not_win_over_tags_on_the_heart(heart_only, order, tmp_path):
    """
    Check that the heart-only tagged study is chosen over the untagged one with more cines.

    The untagged study has more MR cines (the old fallback's pick); the heart-only tagged study is
    chosen whatever the file order, its frames as read alone, the other study's 11 series listed.
    """
    first, last = ('0_', '9_') if order == 'tagged_first' else ('9_', '0_')
    shutil.copytree(heart_only.root / 'tagged', tmp_path / f'{first}tagged')
    shutil.copytree(heart_only.root / 'untagged', tmp_path / f'{last}untagged')
    root = tmp_path
    if order == 'shuffled':
        _shuffle_flat(tmp_path, 5)
        root = tmp_path / 'flat'
    res = read_dicom_dir(root)
    assert res.study_uid == heart_only.tagged.study_uid, res.choice
    assert 'tags on the heart alone' in res.choice and heart_only.untagged.study_uid in res.choice
    _same_frames(res, heart_only.ref)
    assert len(res.not_used) == 11 and all('another study' in r for _, r in res.not_used)
    assert res.complete


def test_mosaic_series_are_refused_per_series(studies, tmp_path):
    """
    Check that Siemens MOSAIC series beside the study are listed once each as MOSAIC.

    Two cines re-saved as Siemens MOSAIC (one by ImageType, one by the private
    NumberOfImagesInMosaic only) and nibabel's real MOSAIC diffusion files beside the study: each
    series listed once as a MOSAIC, the study as read alone.
    """
    import gzip

    import nibabel

    shutil.copytree(studies.root / 'a', tmp_path / 'study')
    uid, for_uid = studies.a.study_uid, studies.a.frame_of_reference_uid

    def private_count(ds, k):
        block = ds.private_block(0x0019, 'SIEMENS MR HEADER', create=True)
        block.add_new(0x0A, 'US', 4)
        return ds.SeriesDescription

    by_type = _save_series(
        _cine(studies.a_paths, 'SA_02'),
        tmp_path / 'mosaic_type',
        'mosaic_type',
        SeriesNumber=50,
        StudyInstanceUID=uid,
        FrameOfReferenceUID=for_uid,
        ImageType=['ORIGINAL', 'PRIMARY', 'M', 'ND', 'MOSAIC'],
    )
    by_private = _save_series(
        _cine(studies.a_paths, 'SA_04'),
        tmp_path / 'mosaic_private',
        'mosaic_private',
        SeriesNumber=51,
        SeriesDescription=private_count,
    )
    data = Path(nibabel.__file__).parent / 'nicom' / 'tests' / 'data'
    real = tmp_path / 'dwi' / 'siemens_dwi_0.dcm'
    real.parent.mkdir()
    real.write_bytes(gzip.decompress((data / 'siemens_dwi_0.dcm.gz').read_bytes()))
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == uid and res.complete
    _same_frames(res, studies.ref_a)
    why = dict(res.not_used)
    assert sorted(why) == sorted([str(by_type[0]), str(by_private[0]), str(real)])
    assert all('Siemens MOSAIC' in r and 'not a cine of one slice' in r for r in why.values())
    assert (
        'ImageType' in why[str(by_type[0])]
        and 'NumberOfImagesInMosaic 4' in why[str(by_private[0])]
    )
    assert 'NumberOfImagesInMosaic 48' in why[str(real)]
    # Nothing but MOSAIC files: a clear error, not a study of them.
    with pytest.raises(DicomReadError, match='no usable cine.*Siemens MOSAIC'):
        read_dicom_dir(real.parent)


def test_a_cine_with_fewer_phases_is_used_by_nearest_trigger_time(studies, tmp_path):
    """
    Check a cine acquired with 2 phases: matched by trigger time or left out with the reason.

    SA 5 acquired with 2 phases at 10 and 340 ms (the study's phases at 0, 333 and 667 ms, a
    quarter interval = 83 ms allowed): its images become phases 1 and 2 of 3, phase 3 missing,
    listed in left_out; at 0 and 500 ms (167 ms off) it is left out with the reason.
    """
    shutil.copytree(studies.root / 'a', tmp_path / 'study')
    shutil.rmtree(tmp_path / 'study' / 'SA_05')
    two = _cine(studies.a_paths, 'SA_05')[:2]
    near = _save_series(
        two,
        tmp_path / 'study' / 'SA_05',
        'near',
        CardiacNumberOfImages=2,
        TriggerTime=lambda ds, k: [10.0, 340.0][k],
    )
    res = read_dicom_dir(tmp_path / 'study')
    got = frames_by_path(res)
    assert [got[str(f)].phase_index for f in near] == [0, 1]
    assert all(got[str(f)].num_phases == 3 for f in near)
    assert [round(got[str(f)].trigger_time, 3) for f in near] == [0.01, 0.34]
    assert len(res.frames) == 32 and len(res.series) == 11 and not res.complete
    ((path, why),) = res.left_out
    assert (
        path == str(near[0])
        and 'nearest its TriggerTime' in why
        and 'phase(s) 3 of 3 missing' in why
    )
    assert res.not_used == []
    ref = frames_by_path(read_dicom_dir(tmp_path / 'study' / 'SA_05'))
    assert all(np.array_equal(got[str(f)].image, ref[str(f)].image) for f in near)
    # Too far from the study's phases: left out, with how far.
    for p in near:
        ds = pydicom.dcmread(p)
        ds.TriggerTime = 500.0 * int(ds.InstanceNumber == two[1].InstanceNumber)
        ds.save_as(p, enforce_file_format=True)
    res = read_dicom_dir(tmp_path / 'study')
    assert (
        len(res.frames) == 30
        and not res.complete
        and [p for p, _ in res.not_used] == [str(near[0])]
    )
    assert "up to 167 ms from the study's" in res.not_used[0][1]


def test_below_the_vote_threshold_the_closest_study_still_wins(heart_only, tmp_path, monkeypatch):
    """
    Check that a vote under the threshold still chooses between studies by the vote.

    Were the heart-only study's vote under the threshold (here: the threshold raised out of
    reach), the choice between studies without a clear tag grid still goes by the vote, not by the
    number of cines: the tagged study, all its cines used, and the choice says how close it came.
    """
    monkeypatch.setattr(dicom_io, '_TAG_STUDY', 1e6)
    monkeypatch.setattr(dicom_io, '_TAG_LINES', 1e6)
    shutil.copytree(heart_only.root / 'untagged', tmp_path / '0_untagged')
    shutil.copytree(heart_only.root / 'tagged', tmp_path / '9_tagged')
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == heart_only.tagged.study_uid, res.choice
    assert (
        'come closest to sharing a tag grid' in res.choice
        and '8 MR cine(s) all used' in res.choice
    )
    _same_frames(res, heart_only.ref)
    assert len(res.not_used) == 11 and res.complete


@pytest.fixture(scope='module')
def single_line(tmp_path_factory, heart_only):
    """
    Write a heart-only study tagged with one family of tag lines (``tag_lines: single``).

    The heart-only fixture's protocol with 6 phases (the vote then reads ED and the next image);
    beside it (``second``) the second single-line series of every slice, the lines turned by 90°
    (``tag_lines: pair``), and (``repeat``) a repeat of the first family in series of its own.
    """
    from mlv_ros.core.sim.protocol import protocol_preset
    from mlv_ros.core.sim.study import line_pair_study

    root = tmp_path_factory.mktemp('single_line')
    protocol = {**HEART_ONLY, 'tag_lines': 'single', 'num_phases': 6}
    kw = {'size': 128, 'num_phases': 6, 'subplanes': 1, 'pixel_spacing': 1.8}
    preset = protocol_preset(protocol)
    study = simulate_study(preset, snr=20.0, seed=23, **kw)
    write_study_dicom(study, root / 'single')
    offset = len(study.series_uids) + 1
    second = line_pair_study(preset, study, 90.0, **kw)
    write_study_dicom(second, root / 'second', series_offset=offset)
    repeat = line_pair_study(preset, study, 0.0, **kw)
    write_study_dicom(repeat, root / 'repeat', series_offset=offset)
    return SimpleNamespace(root=root, study=study, second=second)


def test_single_line_tags_are_found_and_read(single_line, heart_only, tmp_path):
    """
    Check that one family of tag lines wins over an untagged study and is read as such.

    Its cines share tag lines in windows (no grid), so it out-votes the untagged bright-blood study
    with more cines; every frame says it shows one family of lines (``TAGS_LINES``, no second
    image), its pixels those of the study read alone, and the choice says so.
    """
    ed = [f.image for f in single_line.study.frames if f.phase_index == 0]
    nxt = [f.image for f in single_line.study.frames if f.phase_index == 1]
    vote = dicom_io._study_vote([([a, b], 1.8) for a, b in zip(ed, nxt)])
    assert vote.single_line and vote.line >= dicom_io._TAG_LINES
    assert abs(vote.period_mm / 7.0 - 1.0) <= 0.06
    shutil.copytree(single_line.root / 'single', tmp_path / '9_single')
    shutil.copytree(heart_only.root / 'untagged', tmp_path / '0_untagged')
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == single_line.study.study_uid, res.choice
    assert 'single-line tags' in res.choice and '0 of 8 slice(s) paired' in res.choice, res.choice
    assert len(res.frames) == len(single_line.study.frames)
    assert {(f.tag_lines, f.line_image is None) for f in res.frames} == {(TAGS_LINES, True)}


def test_two_single_line_series_of_a_slice_are_paired(single_line, tmp_path):
    """
    Check that the second single-line series of each slice, its lines turned, joins the first.

    Both series of every slice (separate series, numbered after the first): the slices stay 6 SA
    + 2 LA, every frame a line pair whose second image is the second series' pixels of the same
    phase; the series list names the partner. A repeat of the first family instead (the same
    lines in series of their own) is a repeated acquisition: the later kept, not paired.
    """
    shutil.copytree(single_line.root / 'single', tmp_path / 'pair' / 'a')
    shutil.copytree(single_line.root / 'second', tmp_path / 'pair' / 'b')
    res = read_dicom_dir(tmp_path / 'pair')
    assert 'single-line tags' in res.choice and '8 of 8 slice(s) paired' in res.choice, res.choice
    first = read_dicom_dir(single_line.root / 'single')
    other = {_key(f)[1:]: f for f in read_dicom_dir(single_line.root / 'second').frames}
    assert sorted(map(_key, res.frames)) == sorted(map(_key, first.frames))
    for fr in res.frames:
        assert fr.tag_lines == TAGS_LINE_PAIR
        assert np.array_equal(fr.line_image, other[_key(fr)[1:]].image)
    assert len(res.series) == 8 and all(s.line_series_uid for s in res.series)
    assert {s.line_series_uid for s in res.series} == set(single_line.second.series_uids.values())
    shutil.copytree(single_line.root / 'single', tmp_path / 'repeat' / 'a')
    shutil.copytree(single_line.root / 'repeat', tmp_path / 'repeat' / 'b')
    res = read_dicom_dir(tmp_path / 'repeat')
    assert '0 of 8 slice(s) paired' in res.choice, res.choice
    assert {f.tag_lines for f in res.frames} == {TAGS_LINES} and len(res.series) == 8
    assert sum('slice acquired more than once' in w for _, w in res.warnings) == 8


def test_a_tag_grid_wins_over_single_line_tags(single_line, heart_only, tmp_path):
    """Check that a heart-only grid study is taken over a single-line one, whatever the order."""
    shutil.copytree(single_line.root / 'single', tmp_path / '0_single')
    shutil.copytree(heart_only.root / 'tagged', tmp_path / '9_tagged')
    res = read_dicom_dir(tmp_path)
    assert res.study_uid == heart_only.tagged.study_uid, res.choice
    _same_frames(res, heart_only.ref)

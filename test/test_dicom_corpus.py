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
The DICOM bad-input corpus next to a valid study, through the reader and the nodes.

The DICOM bad-input corpus (``test/corpus/dicom_cases.py``) next to a valid study: through the
reader once, then through the real frame_source and tag_detector nodes.

Every bad file must be reported with its reason, every legal-but-odd file must load (with the
pixels it holds), and every valid frame must load exactly as it does without the corpus beside it.
Beside the study, a legal-but-odd case that is not a tagged cine of it (a single image, a cine
with nothing in it) is read but not used: it is listed once, by its first file, with the reason
(the reader's study selection); read alone, it loads.
"""

import shutil
from types import SimpleNamespace

from conftest import spin_until
from corpus.dicom_cases import frames_by_path, write_dicom_corpus
from diagnostic_msgs.msg import DiagnosticArray
from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.io import DicomReadError, read_dicom_dir, write_study_dicom
from mlv_ros.core.sim import simulate_study
import numpy as np
import pydicom
import pytest
from rclpy.parameter import Parameter

REQUIRED_CATEGORIES = {
    'corrupt',
    'truncated',
    'non_image',
    'transfer_syntax',
    'missing_tag',
    'malformed_geometry',
    'contradictory_geometry',
    'mixed_sizes',
    'float_pixels',
    'constant_image',
    'dimensions',
    'pixel_encoding',
    'duplicates',
    'missing_phases',
}
# "loads" cases whose pixels are the template's stored values, only encoded differently.
SAME_PIXELS = {
    'transfer_syntax',
    'missing_tag',
    'contradictory_geometry',
    'dimensions',
    'timing_tags',
    'float_pixels',
}


@pytest.fixture(scope='module')
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp('dicom_corpus')
    study = simulate_study('normal', snr=20.0, size=48, num_phases=3, subplanes=1, seed=2)
    # Of two copies of one instance the reader keeps the first path in sorted order, so the
    # valid study goes in the directory that sorts first.
    good = write_study_dicom(study, root / 'a_valid')
    clean = read_dicom_dir(root / 'a_valid')
    cases = write_dicom_corpus(root / 'b_corpus', good)
    res = read_dicom_dir(root)
    frame_of = frames_by_path(res)
    # The cases that load but are not used beside the study, each read alone.
    alone_of, alone_warned = {}, {}
    for c in cases:
        if c.outcome != 'error' and str(c.files[0]) not in frame_of:
            d = tmp_path_factory.mktemp(f'alone_{c.name}')
            for f in c.files:
                shutil.copy(f, d / f.name)
            alone = read_dicom_dir(d)
            alone_of.update({str(f): frames_by_path(alone)[str(d / f.name)] for f in c.files})
            alone_warned.update({str(c.files[0]): why for _, why in alone.warnings})
    return SimpleNamespace(
        root=root,
        study=study,
        good=good,
        cases=cases,
        res=res,
        frame_of=frame_of,
        alone_of=alone_of,
        alone_warned=alone_warned,
        clean_of=frames_by_path(clean),
        why=dict(res.problems),
        warned=dict(res.warnings),
    )


def _unused(corpus, c) -> bool:
    """Return a legal case read but not used beside the study: listed once, by its first file."""
    return c.outcome != 'error' and str(c.files[0]) not in corpus.frame_of


def test_corpus_is_large_and_covers_every_category(corpus):
    names = [c.name for c in corpus.cases]
    assert len(names) >= 110 and len(set(names)) == len(names)
    assert REQUIRED_CATEGORIES <= {c.category for c in corpus.cases}
    files = [f for c in corpus.cases for f in c.files]
    assert len(set(files)) == len(files) and all(
        f.exists() and f.parent == corpus.root / 'b_corpus' for f in files
    )


def test_every_bad_file_is_reported_with_its_reason(corpus):
    wrong = []
    for c in corpus.cases:
        for f in map(str, c.files):
            if c.outcome == 'error' and c.expect not in corpus.why.get(f, '').lower():
                wrong.append(
                    f'{c.name}: expected {c.expect!r}, got {corpus.why.get(f, "it loaded")!r}'
                )
            elif c.outcome != 'error' and f not in corpus.frame_of and f not in corpus.alone_of:
                wrong.append(f'{c.name}: should load, got {corpus.why.get(f)!r}')
        if _unused(corpus, c):
            why = corpus.why.get(str(min(map(str, c.files))), '')
            # A cine missing a phase is a copy of the study's SA 0 (same place, SeriesNumber, no
            # times): a repeat, the complete original used.
            reasons = (
                ('repeated acquisition',) if c.outcome == 'warn' else ('one frame', 'not tagged')
            )
            if 'not used' not in why or not any(r in why for r in reasons):
                wrong.append(f'{c.name}: should be listed as not used, got {why!r}')
    assert not wrong, '\n'.join(wrong)
    # Nothing else is reported: no valid file, no file twice; an unused series once.
    bad_files = {str(f) for c in corpus.cases if c.outcome == 'error' for f in c.files}
    unused = {min(map(str, c.files)) for c in corpus.cases if _unused(corpus, c)}
    assert len(unused) >= 20  # the single images, the three constant cines, the three SA 0 repeats
    assert sorted(p for p, _ in corpus.res.problems) == sorted(bad_files | unused)


def test_valid_frames_load_bit_identically(corpus):
    assert len(corpus.clean_of) == len(corpus.good) == len(corpus.study.frames)
    for path, sim in zip(map(str, corpus.good), corpus.study.frames):
        got, want = corpus.frame_of[path], corpus.clean_of[path]
        assert got.image.dtype == want.image.dtype and np.array_equal(got.image, want.image), path
        assert (
            got.phase_index,
            got.num_phases,
            got.trigger_time,
            got.cycle_duration,
            got.series_uid,
        ) == (
            want.phase_index,
            want.num_phases,
            want.trigger_time,
            want.cycle_duration,
            want.series_uid,
        )
        for name in ('image_position', 'row_direction', 'column_direction'):
            assert np.array_equal(getattr(got.geometry, name), getattr(want.geometry, name))
        # ... and as simulated, to the writer's quantisation (1/1000 of M0).
        np.testing.assert_allclose(got.image, sim.image, atol=0.5e-3 + 1e-6)
        assert got.phase_index == sim.phase_index


def test_odd_but_legal_files_load_with_their_pixels(corpus):
    template = corpus.frame_of[str(corpus.good[0])].image
    for c in corpus.cases:
        if c.outcome == 'error':
            continue
        images = [
            (corpus.alone_of if _unused(corpus, c) else corpus.frame_of)[str(f)].image
            for f in c.files
        ]
        if c.category in SAME_PIXELS:
            for img in images:
                assert img.dtype == np.float32 and np.array_equal(img, template), c.name
        elif c.category == 'constant_image':
            assert all(np.ptp(img) == 0 for img in images), c.name


def test_missing_phases_keep_their_indices_and_are_reported(corpus):
    """
    Check that cines missing phases keep their phase indices and are reported.

    Each read alone (beside the study they repeat its SA 0, whose complete cine is used: the
    one warning).
    """
    cases = [c for c in corpus.cases if c.outcome == 'warn']
    assert len(cases) == 3
    for c in cases:
        assert c.expect in corpus.alone_warned.get(str(c.files[0]), ''), c.name
        for f in c.files:
            inst = int(pydicom.dcmread(f, stop_before_pixels=True).InstanceNumber)
            frame = corpus.alone_of[str(f)]
            assert (frame.phase_index, frame.num_phases) == (inst - 1, 3), c.name
    ((path, why),) = corpus.res.warnings
    assert (
        path == str(corpus.good[0])
        and 'slice acquired more than once' in why
        and 'most images' in why
    )


def test_max_pixels_refuses_large_images_before_reading_them(corpus):
    valid = corpus.root / 'a_valid'
    with pytest.raises(DicomReadError) as err:
        read_dicom_dir(valid, max_pixels=48 * 48 - 1)
    assert len(err.value.problems) == len(corpus.good)
    assert all('more than max_pixels = 2303' in why for _, why in err.value.problems)
    assert len(read_dicom_dir(valid, max_pixels=48 * 48).frames) == len(corpus.good)
    for bad in (0, -5, 1.5, True):
        with pytest.raises(ValueError, match='max_pixels must be a positive integer'):
            read_dicom_dir(valid, max_pixels=bad)


def test_frame_source_reports_each_bad_file_and_publishes_every_valid_frame(
    corpus, ros_context, executor
):
    from mlv_ros.nodes.frame_source import FrameSource
    from mlv_ros.nodes.tag_detector import TagDetector
    import rclpy

    frames, statuses, points = [], [], []
    sink = rclpy.create_node('corpus_sink', context=ros_context)
    sink.create_subscription(TaggedFrame, qos.FRAMES, frames.append, qos.stream_qos())
    sink.create_subscription(TagPoints, qos.TAG_POINTS, points.append, qos.stream_qos())
    sink.create_subscription(
        DiagnosticArray,
        qos.DIAGNOSTICS,
        lambda m: statuses.extend(m.status),
        qos.diagnostics_qos(),
    )
    detector = TagDetector(context=ros_context)
    source = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='dicom'),
            Parameter('path', value=str(corpus.root)),
            Parameter('wait_for_subscribers', value=2),
            Parameter('wait_timeout_s', value=20.0),
            Parameter('exit_when_done', value=True),
        ],
    )
    for node in (sink, detector, source):
        executor.add_node(node)
    n = len(corpus.res.frames)

    # (A cine missing a phase holds its later frames back in the detector: not every frame
    # yields tag points, so the wait is on the frames.)
    assert spin_until(executor, lambda: source.done and len(frames) == n, 30), (
        f'{len(frames)}/{n} frames, done={source.done}'
    )

    def reported(message):
        return {
            kv.value
            for s in statuses
            if s.message == message
            for kv in s.values
            if kv.key == 'file'
        }

    skipped, incomplete = (
        reported('skipped DICOM file'),
        reported('DICOM series used with a warning'),
    )
    unused = reported('DICOM series not used')
    assert unused == {p for p, _ in corpus.res.not_used} and len(unused) >= 20
    assert skipped | unused == {p for p, _ in corpus.res.problems} and not skipped & unused
    assert incomplete == {p for p, _ in corpus.res.warnings}
    # Every frame the reader loaded (valid and legal-but-odd) was published, pixels intact.
    got = {
        (f.series_uid, f.view, f.slice_index, f.phase_index): conversions.msg_to_frame(f)
        for f in frames
    }
    assert len(got) == n
    for path in map(str, corpus.good):
        want = corpus.frame_of[path]
        fr = got[(want.series_uid, want.view, want.slice_index, want.phase_index)]
        assert np.array_equal(fr.image, want.image), path
    # Cines with nothing in them are not published beside the tagged study: the reader says why
    # (read alone they load; the tag detector on such images: corpus/message_cases.py).
    const = [c for c in corpus.cases if c.detector_status]
    assert len(const) == 3 and not any(str(f) in corpus.frame_of for c in const for f in c.files)
    for c in const:
        assert 'the ED image is constant' in corpus.why[str(c.files[0])]
        assert str(c.files[0]) in unused

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
Property tests of the DICOM reader: exact read-back, no raise on byte mutations.

Property tests of the DICOM reader: what the writer writes reads back exactly, and no byte
mutation of a valid file makes the reader raise or lose the valid files beside it.
"""

from pathlib import Path
import tempfile

from corpus.dicom_cases import frames_by_path
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.io.dicom import frame_to_dataset, read_dicom_dir
from mlv_ros.core.types import Frame, VIEW_SA
import numpy as np
import pydicom
import pytest


def _rotation(q) -> np.ndarray:
    """Rotation matrix of a (not necessarily unit) quaternion (w, x, y, z), shape (3, 3)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


quaternions = st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
spacings = st.floats(0.05, 10.0, allow_nan=False)


@st.composite
def frames(draw):
    rows, cols = draw(st.integers(1, 24)), draw(st.integers(1, 24))
    r = _rotation(draw(quaternions))
    geom = SliceGeometry(
        np.array(draw(st.tuples(*[st.floats(-1000, 1000, allow_nan=False)] * 3))),
        r[:, 0],
        r[:, 1],
        draw(spacings),
        draw(spacings),
        draw(st.floats(0.1, 20.0)),
    )
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if draw(st.booleans()):  # stored as it is (uint16, slope 1), the full range
        image = rng.integers(0, 65536, size=(rows, cols), dtype=np.uint16)
    else:  # float intensities, stored as round(value · 1000) with RescaleSlope 0.001
        image = (rng.integers(0, 65536, size=(rows, cols)) / 1000.0).astype(np.float32)
    num_phases = draw(st.integers(1, 50))
    return Frame(
        image=image,
        geometry=geom,
        view=VIEW_SA,
        slice_index=0,
        phase_index=draw(st.integers(0, num_phases - 1)),
        num_phases=num_phases,
        trigger_time=draw(st.floats(0, 2.0)),
        cycle_duration=2.0,
        series_uid=pydicom.uid.generate_uid(),
    )


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(frame=frames())
def test_written_frames_read_back_exactly(frame):
    with tempfile.TemporaryDirectory() as d:
        frame_to_dataset(frame).save_as(Path(d) / 'x.dcm', enforce_file_format=True)
        res = read_dicom_dir(d)
    assert res.problems == [] and len(res.frames) == 1
    got = res.frames[0]
    if frame.image.dtype == np.uint16:
        assert got.image.dtype == np.uint16 and np.array_equal(got.image, frame.image)
    else:  # the writer's quantisation, nothing more: round(v · 1000) / 1000 in float32
        want = (np.rint(frame.image.astype(np.float64) * 1000.0) * 0.001).astype(np.float32)
        assert got.image.dtype == np.float32 and np.array_equal(got.image, want)
    g, w = got.geometry, frame.geometry
    # DS holds 16 characters: positions to ~1e-10 mm at 1000 mm, unit vectors to ~1e-13.
    np.testing.assert_allclose(g.image_position, w.image_position, rtol=0, atol=1e-6)
    np.testing.assert_allclose(g.row_direction, w.row_direction, rtol=0, atol=1e-9)
    np.testing.assert_allclose(g.column_direction, w.column_direction, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        [g.row_spacing, g.column_spacing, g.slice_thickness],
        [w.row_spacing, w.column_spacing, w.slice_thickness],
        rtol=1e-12,
    )
    assert (
        abs(got.trigger_time - frame.trigger_time) < 1e-9
        and got.cycle_duration == frame.cycle_duration
    )
    # One image of a series announcing more phases: its InstanceNumber places it.
    assert (got.phase_index, got.num_phases) == (frame.phase_index, frame.num_phases)


def _valid_files(d: Path) -> list[Path]:
    """
    Write two 3-phase 16×16 cines and the first image of a third (to mutate); return its path last.

    One study and frame of reference: a mutant can then change which study or frame of reference
    a reader chooses only by damaging its own identifiers, and single frames that are not cines
    (which a reader rightly leaves out beside cines) are not what the mutant competes with.
    """
    rng = np.random.default_rng(5)
    study = pydicom.uid.generate_uid(entropy_srcs=['property study'])
    frame_of_reference = pydicom.uid.generate_uid(entropy_srcs=['property frame'])
    paths = []
    for k in range(3):
        geom = SliceGeometry(
            np.array([0.0, 0.0, 8.0 * k]),
            np.array([1.0, 0, 0]),
            np.array([0, 1.0, 0]),
            1.5,
            1.5,
            8.0,
        )
        for phase in range(3 if k < 2 else 1):
            fr = Frame(
                image=rng.random((16, 16)).astype(np.float32),
                geometry=geom,
                view=VIEW_SA,
                slice_index=k,
                phase_index=phase,
                num_phases=3,
                trigger_time=0.3 * phase,
                cycle_duration=1.0,
                series_uid=pydicom.uid.generate_uid(entropy_srcs=['property', str(k)]),
            )
            paths.append(d / f'valid_{k}_{phase}.dcm')
            frame_to_dataset(
                fr, study_uid=study, frame_of_reference_uid=frame_of_reference
            ).save_as(paths[-1], enforce_file_format=True)
    return paths


@pytest.fixture(scope='module')
def mutant_dir(tmp_path_factory):
    """Two valid cines, their images as read alone, and the bytes of a third cine's image."""
    d = tmp_path_factory.mktemp('dicom_mutants')
    valid = _valid_files(d)
    original = valid[-1].read_bytes()
    valid[-1].unlink()
    clean = {f: fr.image for f, fr in frames_by_path(read_dicom_dir(d)).items()}
    assert len(clean) == 6
    return d, clean, original


positions = st.integers(0, 10**6)
mutations = st.lists(
    st.one_of(
        st.tuples(st.just('flip'), positions, st.integers(0, 7)),
        st.tuples(st.just('insert'), positions, st.binary(min_size=1, max_size=16)),
        st.tuples(st.just('delete'), positions, st.integers(1, 64)),
        st.tuples(st.just('overwrite'), positions, st.binary(min_size=1, max_size=8)),
        st.tuples(st.just('truncate'), positions, st.just(None)),
    ),
    min_size=1,
    max_size=4,
)


def mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for kind, pos, arg in ops:
        pos %= max(len(b), 1)
        if kind == 'flip' and b:
            b[pos] ^= 1 << arg
        elif kind == 'insert':
            b[pos:pos] = arg
        elif kind == 'delete':
            del b[pos:pos + arg]
        elif kind == 'overwrite':
            b[pos:pos + len(arg)] = arg
        elif kind == 'truncate':
            del b[pos:]
    return bytes(b)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ops=mutations)
def test_mutated_file_is_reported_or_loaded_and_never_breaks_the_rest(mutant_dir, ops):
    d, clean, original = mutant_dir
    mutant = d / 'mutant.dcm'
    mutant.write_bytes(mutate(original, ops))
    res = read_dicom_dir(d)  # must not raise
    frames = frames_by_path(res)
    for path, image in clean.items():
        assert np.array_equal(frames[path].image, image), path
    reported = dict(res.problems)
    assert set(reported) <= {str(mutant)}
    if str(mutant) in reported:
        assert 'unexpected error' not in reported[str(mutant)], reported[str(mutant)]
    else:  # a mutation the format tolerates (e.g. in a text value): it loads as a sane image
        img = frames[str(mutant)].image
        assert img.ndim == 2 and img.size > 0
        assert img.dtype.kind != 'f' or np.all(np.isfinite(img))

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
Round trips (bit-exact) and bad input for every numpy ⇄ message conversion.

Round trips (bit-exact) and bad input for every numpy ⇄ message conversion, including a pass
through real CDR serialisation (what every rclpy hop does).
"""

import array

from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import MotionMetrics, TaggedFrame
from mlv_ros import conversions as cv
from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import Frame, ModelState, TagPointSet, VIEW_LA
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Image, PointCloud2, PointField

RNG = np.random.default_rng(7)


def cdr(msg):
    """Serialise and deserialise as an rclpy publisher/subscriber pair would."""
    return deserialize_message(serialize_message(msg), type(msg))


def oblique_geometry():
    row = np.array([0.6, 0.8, 0.0])
    col = np.array([0.0, 0.0, -1.0])
    return SliceGeometry(np.array([-120.5, 33.25, 71.0]), row, col, 1.3, 1.25, 6.0)


# ----------------------------------------------------------------------------- Image
@pytest.mark.parametrize(
    'dtype,encoding', [(np.uint16, 'mono16'), (np.float32, '32FC1'), (np.uint8, 'mono8')]
)
def test_image_round_trip_bit_exact(dtype, encoding):
    if dtype is np.float32:
        img = RNG.normal(size=(256, 200)).astype(dtype)
    else:
        img = RNG.integers(0, np.iinfo(dtype).max, size=(256, 200), endpoint=True).astype(dtype)
    msg = cdr(cv.image_to_msg(img))
    assert msg.encoding == encoding
    assert msg.step == 200 * np.dtype(dtype).itemsize
    assert msg.is_bigendian == 0
    back = cv.msg_to_image(msg)
    assert back.dtype == dtype and back.shape == img.shape
    assert back.tobytes() == img.tobytes()


def test_image_with_row_padding_and_big_endian():
    img = RNG.integers(0, 65535, size=(5, 7)).astype(np.uint16)
    padded = np.zeros((5, 9), dtype='>u2')
    padded[:, :7] = img
    msg = Image(
        height=5, width=7, encoding='mono16', is_bigendian=1, step=18, data=padded.tobytes()
    )
    back = cv.msg_to_image(msg)
    np.testing.assert_array_equal(back, img)
    assert back.dtype.isnative


@pytest.mark.parametrize(
    'mutate,match',
    [
        ({'encoding': 'rgb8'}, 'unsupported image encoding'),
        ({'step': 100}, 'step 100 is smaller'),
        ({'step': 129}, 'not a multiple'),
        ({'height': 0}, 'zero size'),
        ({'data': b'\0' * 10}, 'expected height·step'),
    ],
)
def test_image_bad_messages(mutate, match):
    msg = cv.image_to_msg(np.zeros((4, 64), np.uint16))
    for k, v in mutate.items():
        setattr(msg, k, v)
    with pytest.raises(ValueError, match=match):
        cv.msg_to_image(msg)


def test_image_nan_rejected_unless_allowed():
    img = np.ones((4, 4), np.float32)
    img[1, 2] = np.nan
    msg = cv.image_to_msg(img)
    with pytest.raises(ValueError, match='1 non-finite'):
        cv.msg_to_image(msg)
    assert np.isnan(cv.msg_to_image(msg, allow_nonfinite=True)[1, 2])


@pytest.mark.parametrize(
    'arr,match',
    [
        (np.zeros((2, 3, 3), np.uint16), '2-D'),
        (np.zeros((0, 3), np.uint16), 'empty'),
        (np.zeros((3, 3), np.int64), 'no image encoding'),
    ],
)
def test_image_bad_arrays(arr, match):
    with pytest.raises(ValueError, match=match):
        cv.image_to_msg(arr)


def test_image_encoding_must_match_dtype():
    with pytest.raises(ValueError, match='needs dtype'):
        cv.image_to_msg(np.zeros((3, 3), np.float32), encoding='mono16')


@settings(max_examples=40, deadline=None)
@given(hnp.arrays(np.uint16, hnp.array_shapes(min_dims=2, max_dims=2, min_side=1, max_side=40)))
def test_image_round_trip_property(img):
    np.testing.assert_array_equal(cv.msg_to_image(cdr(cv.image_to_msg(img))), img)


# ----------------------------------------------------------------------------- PointCloud2
def motion_cloud(n=1000):
    return cv.structured(
        {k: RNG.normal(size=n) * 30 for k in ('x', 'y', 'z', 'dx', 'dy', 'dz', 'err')}
    )


def test_cloud_round_trip_bit_exact():
    pts = motion_cloud()
    msg = cdr(cv.cloud_to_msg(pts, cv.make_header(1.5)))
    assert (msg.height, msg.width, msg.point_step) == (1, 1000, 28)
    assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'dx', 'dy', 'dz', 'err']
    assert all(f.datatype == PointField.FLOAT32 and f.count == 1 for f in msg.fields)
    assert msg.header.frame_id == 'patient'
    back = cv.msg_to_cloud(msg, required=('x', 'y', 'z'))
    assert back.tobytes() == pts.tobytes()
    np.testing.assert_array_equal(cv.xyz(back), cv.xyz(pts))


def test_cloud_mixed_dtypes_and_empty():
    pts = np.zeros(3, dtype=[('x', np.float32), ('id', np.int32), ('w', np.float64)])
    pts['id'] = [4, -5, 6]
    back = cv.msg_to_cloud(cdr(cv.cloud_to_msg(pts)))
    assert back.tobytes() == pts.tobytes()
    empty = cv.msg_to_cloud(cdr(cv.cloud_to_msg(motion_cloud(0))), required=('x',))
    assert empty.shape == (0,)


def test_cloud_reads_foreign_layout_with_padding():
    # A PointCloud2 as a PCL publisher writes it: x y z + 4 bytes padding, 2 rows.
    rec = np.zeros(
        (2, 3),
        dtype=np.dtype(
            {
                'names': ['x', 'y', 'z'],
                'formats': ['<f4'] * 3,
                'offsets': [0, 4, 8],
                'itemsize': 16,
            }
        ),
    )
    rec['x'] = np.arange(6).reshape(2, 3)
    fields = [
        PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, n in enumerate('xyz')
    ]
    msg = PointCloud2(
        height=2, width=3, fields=fields, point_step=16, row_step=48, data=rec.tobytes()
    )
    back = cv.msg_to_cloud(msg, required=('x', 'y', 'z'))
    np.testing.assert_array_equal(back['x'], np.arange(6))


def test_cloud_bad_messages():
    msg = cv.cloud_to_msg(motion_cloud(10))
    with pytest.raises(ValueError, match=r"lacks field\(s\) \['strain'\]"):
        cv.msg_to_cloud(msg, required=('x', 'strain'))
    short = cv.cloud_to_msg(motion_cloud(10))
    short.data = short.data[:-4]
    with pytest.raises(ValueError, match='expected row_step·height'):
        cv.msg_to_cloud(short)
    bad = cv.cloud_to_msg(motion_cloud(10))
    bad.fields[1].offset = 26
    with pytest.raises(ValueError, match='does not fit'):
        cv.msg_to_cloud(bad)
    counted = cv.cloud_to_msg(motion_cloud(10))
    counted.fields[0].count = 3
    with pytest.raises(ValueError, match='count 3'):
        cv.msg_to_cloud(counted)
    unknown = cv.cloud_to_msg(motion_cloud(10))
    unknown.fields[0].datatype = 42
    with pytest.raises(ValueError, match='unknown PointField datatype 42'):
        cv.msg_to_cloud(unknown)


def test_cloud_bad_arrays():
    pts = motion_cloud(5)
    pts['dx'][3] = np.inf
    with pytest.raises(ValueError, match="'dx' has 1 non-finite"):
        cv.cloud_to_msg(pts)
    with pytest.raises(ValueError, match='structured'):
        cv.cloud_to_msg(np.zeros((5, 3), np.float32))
    with pytest.raises(ValueError, match='equal length'):
        cv.structured({'x': np.zeros(3), 'y': np.zeros(4)})
    with pytest.raises(ValueError, match='cannot represent'):
        cv.cloud_to_msg(np.zeros(2, dtype=[('x', np.complex64)]))


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 300),
    st.lists(st.sampled_from(['f4', 'f8', 'i4', 'u2', 'u1']), min_size=1, max_size=5),
)
def test_cloud_round_trip_property(n, formats):
    dtype = np.dtype([(f'f{i}', fmt) for i, fmt in enumerate(formats)])
    raw = np.random.default_rng(n).integers(0, 200, size=n * dtype.itemsize, dtype=np.uint8)
    pts = np.frombuffer(raw.tobytes(), dtype=dtype).copy()
    for name in dtype.names:  # keep floats finite
        if dtype[name].kind == 'f':
            pts[name] = np.nan_to_num(pts[name], nan=0.0, posinf=0.0, neginf=0.0)
    assert cv.msg_to_cloud(cdr(cv.cloud_to_msg(pts))).tobytes() == pts.tobytes()


# ----------------------------------------------------------------------------- custom messages
def test_geometry_round_trip_and_validation():
    g = oblique_geometry()
    back = cv.msg_to_geometry(cdr(cv.geometry_to_msg(g)))
    for name in ('image_position', 'row_direction', 'column_direction'):
        assert getattr(back, name).tobytes() == getattr(g, name).tobytes()
    assert (back.row_spacing, back.column_spacing, back.slice_thickness) == (1.3, 1.25, 6.0)
    msg = cv.geometry_to_msg(g)
    msg.row_direction = np.array([1.0, 1.0, 0.0])
    with pytest.raises(ValueError, match='unit vector'):
        cv.msg_to_geometry(msg)
    msg = cv.geometry_to_msg(g)
    msg.row_spacing = 0.0
    with pytest.raises(ValueError, match='row_spacing must be a positive'):
        cv.msg_to_geometry(msg)


def test_frame_round_trip():
    img = RNG.integers(0, 4096, size=(64, 48)).astype(np.uint16)
    f = Frame(
        image=img,
        geometry=oblique_geometry(),
        view=VIEW_LA,
        slice_index=2,
        phase_index=7,
        num_phases=25,
        trigger_time=0.336,
        cycle_duration=0.96,
        series_uid='1.2.3.4',
        num_sa_slices=8,
        num_la_slices=3,
    )
    msg = cdr(cv.frame_to_msg(f, stamp=12.25))
    assert isinstance(msg, TaggedFrame) and cv.from_time(msg.header.stamp) == 12.25
    back = cv.msg_to_frame(msg)
    assert back.image.tobytes() == img.tobytes()
    for name in (
        'view',
        'slice_index',
        'phase_index',
        'num_phases',
        'trigger_time',
        'cycle_duration',
        'series_uid',
        'num_sa_slices',
        'num_la_slices',
    ):
        assert getattr(back, name) == getattr(f, name), name


@pytest.mark.parametrize('dtype', [np.uint8, np.uint16, np.float32])
def test_line_pair_frames_travel_as_two_channels(dtype):
    """
    Check a line pair's two images: one two-channel image out, both bit-exact back.

    Over CDR (an independent reader, rosbags, sees the ``8UC2`` / ``16UC2`` / ``32FC2`` image
    of the frame's shape); a single-line frame keeps one channel; a mismatched second image, a
    tag_lines value outside the TAGS_* set and an encoding that contradicts tag_lines are refused.
    """
    from dataclasses import replace

    from mlv_ros.core.types import TAGS_LINE_PAIR, TAGS_LINES

    a = RNG.integers(0, 200, size=(6, 5)).astype(dtype)
    b = RNG.integers(0, 200, size=(6, 5)).astype(dtype)
    f = Frame(
        image=a, geometry=oblique_geometry(), view=VIEW_LA, slice_index=0, phase_index=1,
        num_phases=3, tag_lines=TAGS_LINE_PAIR, line_image=b,
    )
    msg = cdr(cv.frame_to_msg(f))
    assert msg.tag_lines == TaggedFrame.TAGS_LINE_PAIR == TAGS_LINE_PAIR
    assert (msg.image.height, msg.image.width, msg.image.encoding[-2:]) == (6, 5, 'C2')
    back = cv.msg_to_frame(msg)
    assert back.tag_lines == TAGS_LINE_PAIR and back.image.dtype == a.dtype
    assert np.array_equal(back.image, a) and np.array_equal(back.line_image, b)
    one = cv.msg_to_frame(cdr(cv.frame_to_msg(replace(f, tag_lines=TAGS_LINES))))
    assert one.tag_lines == TAGS_LINES and one.line_image is None and np.array_equal(one.image, a)
    with pytest.raises(ValueError, match='line_image'):
        cv.frame_to_msg(replace(f, line_image=b[:5]))
    with pytest.raises(ValueError, match='tag_lines'):
        cv.frame_to_msg(replace(f, tag_lines=3))
    bad = cdr(cv.frame_to_msg(f))
    bad.tag_lines = TAGS_LINES
    with pytest.raises(ValueError, match='does not fit tag_lines'):
        cv.msg_to_frame(bad)


def test_frame_bad_indices():
    f = Frame(
        image=np.zeros((4, 4), np.uint16),
        geometry=oblique_geometry(),
        view=5,
        slice_index=0,
        phase_index=0,
        num_phases=2,
    )
    with pytest.raises(ValueError, match='view must be'):
        cv.frame_to_msg(f)
    f.view, f.phase_index = VIEW_LA, 2
    with pytest.raises(ValueError, match=r'phase_index 2 outside \[0, 2\)'):
        cv.frame_to_msg(f)


def make_points(n=50):
    g, rc = oblique_geometry(), RNG.uniform(0, 256, (n, 2))
    return TagPointSet(
        view=0,
        slice_index=3,
        phase_index=4,
        num_phases=20,
        geometry=g,
        pixel_rc=rc,
        position=g.pixel_to_patient(rc),
        track_id=np.arange(n, dtype=np.int32)[::-1].copy(),
        confidence=RNG.uniform(0, 1, n).astype(np.float32),
        status='',
        stamp=3.5,
        num_sa_slices=8,
        num_la_slices=3,
    )


def test_tagpoints_round_trip():
    p = make_points()
    back = cv.msg_to_tagpoints(cdr(cv.tagpoints_to_msg(p)))
    for name in ('pixel_rc', 'position', 'track_id', 'confidence'):
        a, b = getattr(p, name), getattr(back, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    assert (back.view, back.slice_index, back.phase_index, back.stamp) == (0, 3, 4, 3.5)
    empty = TagPointSet(
        view=0,
        slice_index=0,
        phase_index=0,
        num_phases=1,
        geometry=oblique_geometry(),
        status='no tags found',
    )
    back = cv.msg_to_tagpoints(cdr(cv.tagpoints_to_msg(empty)))
    assert len(back) == 0 and back.status == 'no tags found'


def test_tagpoints_carry_tag_line_normals():
    p = make_points(4)
    n = np.cross(p.geometry.normal, RNG.normal(size=(4, 3)))
    p.line_normal = n / np.linalg.norm(n, axis=1, keepdims=True)
    p.line_normal[2] = np.nan  # an intersection among line points
    msg = cv.tagpoints_to_msg(p)
    back = cv.msg_to_tagpoints(cdr(msg))
    sent = p.line_normal.astype(np.float32).astype(np.float64)  # the message's float32
    assert back.line_normal.dtype == np.float64
    assert back.line_normal.tobytes() == sent.tobytes()
    assert cv.msg_to_tagpoints(cdr(cv.tagpoints_to_msg(make_points(4)))).line_normal.shape == (
        0,
        3,
    )  # grid points: none sent, none read
    for bad, match in (
        (p.line_normal[:3], r'3 per point'),
        (2 * np.nan_to_num(p.line_normal), 'unit vectors or all NaN'),
    ):
        msg.line_normal = array.array('f', np.ravel(bad).astype(np.float32).tobytes())
        with pytest.raises(ValueError, match=match):
            cv.msg_to_tagpoints(msg)


def test_rosbags_reads_tagpoints_with_and_without_line_normals():
    """An independent reader (rosbags) takes what rmw serialises, normals or none, any run_id."""
    from pathlib import Path

    from rclpy.serialization import serialize_message
    from rosbags.typesys import get_types_from_msg, get_typestore, Stores

    msgs = Path(__file__).resolve().parents[1] / 'msg_schemas' / 'msg'
    store = get_typestore(Stores.ROS2_JAZZY)
    for name in ('SliceGeometry', 'TagPoints'):
        text = (msgs / f'{name}.msg').read_text()
        store.register(get_types_from_msg(text, f'mlv_msgs/msg/{name}'))
    for n in (1, 2, 3):  # not 0: empty float64[] position (README, Recordings: a known limit)
        for run_id in ('', 'a', 'ab', 'abc'):
            p = make_points(n)
            p.run_id = run_id
            if n % 2:
                p.line_normal = np.tile(p.geometry.row_direction, (n, 1))
            raw = serialize_message(cv.tagpoints_to_msg(p))
            got = store.deserialize_cdr(raw, 'mlv_msgs/msg/TagPoints')
            assert got.run_id == run_id and len(got.line_normal) == (3 * n if n % 2 else 0)


def test_tagpoints_inconsistent_lengths():
    p = make_points(5)
    p.confidence = p.confidence[:4]
    with pytest.raises(ValueError, match='disagree'):
        cv.tagpoints_to_msg(p)
    msg = cv.tagpoints_to_msg(make_points(5))
    msg.position = msg.position[:-1]
    with pytest.raises(ValueError, match=r'position 14 \(want 15\)'):
        cv.msg_to_tagpoints(msg)
    p = make_points(5)
    p.position[2, 1] = np.nan
    with pytest.raises(ValueError, match='tag position has 1 non-finite'):
        cv.tagpoints_to_msg(p)


def test_model_state_round_trip_and_validation():
    q = RNG.normal(size=4)
    s = ModelState(
        phase_index=3,
        num_phases=25,
        translation=np.array([1.5, -2.0, 30.25]),
        rotation=q / np.linalg.norm(q),
        a0=31.2,
        a1=0.9,
        a2=1.1,
        a3=2.7,
        tau=-0.031,
        iterations=17,
        residual=0.042,
        converged=True,
        num_particles=5000,
        num_control_points=812,
    )
    msg = cdr(cv.model_state_to_msg(s, stamp=2.0))
    assert isinstance(msg, ModelStateMsg)
    back = cv.msg_to_model_state(msg)
    assert back.rotation.tobytes() == s.rotation.tobytes()
    assert back.translation.tobytes() == s.translation.tobytes()
    for name in (
        'a0',
        'a1',
        'a2',
        'a3',
        'tau',
        'iterations',
        'residual',
        'converged',
        'num_particles',
    ):
        assert getattr(back, name) == getattr(s, name)
    s.rotation = np.array([1.0, 1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match='unit quaternion'):
        cv.model_state_to_msg(s)
    s.rotation, s.tau = np.array([1.0, 0, 0, 0]), np.nan
    with pytest.raises(ValueError, match='non-finite'):
        cv.model_state_to_msg(s)


def make_metrics(levels=10, segments=17):
    m = {name: RNG.normal(size=levels) for name in cv.METRIC_LEVEL_FIELDS}
    m.update({name: RNG.normal(size=segments) for name in cv.METRIC_SEGMENT_FIELDS})
    m.update({name: float(RNG.normal()) for name in cv.METRIC_SCALAR_FIELDS})
    m.update(phase_index=5, num_phases=25)
    return m


def test_metrics_round_trip():
    m = make_metrics()
    msg = cdr(cv.metrics_to_msg(m))
    assert isinstance(msg, MotionMetrics)
    back = cv.msg_to_metrics(msg)
    for name in (*cv.METRIC_LEVEL_FIELDS, *cv.METRIC_SEGMENT_FIELDS):
        assert back[name].tobytes() == m[name].tobytes(), name
    for name in cv.METRIC_SCALAR_FIELDS:
        assert back[name] == m[name]
    assert (
        cv.msg_to_metrics(cdr(cv.metrics_to_msg(make_metrics(segments=0))))['segment_ecc'].size
        == 0
    )


def test_metrics_bad_input():
    m = make_metrics()
    m['twist_deg'] = m['twist_deg'][:-1]
    with pytest.raises(ValueError, match='different lengths'):
        cv.metrics_to_msg(m)
    m = make_metrics(segments=16)
    with pytest.raises(ValueError, match='0 or 17'):
        cv.metrics_to_msg(m)
    m = make_metrics()
    m['sa_radius_mm'][0] = np.nan
    with pytest.raises(ValueError, match='sa_radius_mm has 1 non-finite'):
        cv.metrics_to_msg(m)


def test_study_id_round_trip_through_every_message():
    """
    Check run isolation: every message carries its study's id through CDR and back.

    Run isolation: every message of a study carries its id, through CDR and back; an id a
    message cannot carry sensibly is refused.
    """
    study = '1.2.826.0.1.3680043.8.498.12345'
    img = RNG.integers(0, 4096, size=(8, 8)).astype(np.uint16)
    f = Frame(
        image=img,
        geometry=oblique_geometry(),
        view=VIEW_LA,
        slice_index=1,
        phase_index=2,
        num_phases=5,
        study_id=study,
    )
    assert (
        cdr(cv.frame_to_msg(f)).study_id == study
        and cv.msg_to_frame(cdr(cv.frame_to_msg(f))).study_id == study
    )
    p = make_points(3)
    p.study_id = study
    assert cv.msg_to_tagpoints(cdr(cv.tagpoints_to_msg(p))).study_id == study
    s = ModelState(phase_index=1, num_phases=5, study_id=study)
    assert cv.msg_to_model_state(cdr(cv.model_state_to_msg(s))).study_id == study
    m = make_metrics()
    assert cv.msg_to_metrics(cdr(cv.metrics_to_msg({**m, 'study_id': study})))['study_id'] == study
    assert (
        cv.msg_to_metrics(cdr(cv.metrics_to_msg(m)))['study_id'] == ''
    )  # optional: unknown study
    # ... and the run's id alongside.
    f.run_id = p.run_id = s.run_id = '9f3a11c0d2e4b5a6'
    assert cv.msg_to_frame(cdr(cv.frame_to_msg(f))).run_id == f.run_id
    assert cv.msg_to_tagpoints(cdr(cv.tagpoints_to_msg(p))).run_id == f.run_id
    assert cv.msg_to_model_state(cdr(cv.model_state_to_msg(s))).run_id == f.run_id
    assert (
        cv.msg_to_metrics(cdr(cv.metrics_to_msg({**m, 'run_id': f.run_id})))['run_id'] == f.run_id
    )
    s.run_id = 'a\tb'
    with pytest.raises(ValueError, match='run_id .* non-printable'):
        cv.model_state_to_msg(s)
    s.run_id = ''
    assert (
        cv.msg_to_frame(
            cdr(
                cv.frame_to_msg(
                    Frame(
                        image=img,
                        geometry=oblique_geometry(),
                        view=0,
                        slice_index=0,
                        phase_index=0,
                        num_phases=2,
                    )
                )
            )
        ).study_id
        == ''
    )
    for bad, why in (('x' * (cv.MAX_STUDY_ID + 1), 'at most'), ('a\nb', 'non-printable')):
        s.study_id = bad
        with pytest.raises(ValueError, match=why):
            cv.model_state_to_msg(s)
        msg = cv.frame_to_msg(f)
        msg.study_id = bad
        with pytest.raises(ValueError, match=why):
            cv.msg_to_frame(msg)


def test_segment_origin_and_findings_round_trip():
    """
    Check that the registered state's segment origin and per-segment findings survive CDR.

    The registered state's segment origin and the per-segment findings (NaN = not measured,
    classes as uint8 codes) survive CDR; bad codes and lengths are refused.
    """
    from mlv_ros.core.analysis.findings import CLASS_CODES, FINDING_ARRAY_FIELDS, Findings
    from mlv_ros.core.types import SEGMENT_ORIGIN_CODES

    s = ModelState(
        phase_index=0,
        num_phases=20,
        segment_origin=SEGMENT_ORIGIN_CODES['detected'],
        segment_origin_confidence=0.73,
    )
    back = cv.msg_to_model_state(cdr(cv.model_state_to_msg(s)))
    assert back.segment_origin == 2 and back.segment_origin_confidence == 0.73
    assert (
        cv.msg_to_model_state(cdr(cv.model_state_to_msg(ModelState(num_phases=2)))).segment_origin
        == 0
    )
    with pytest.raises(ValueError, match='segment_origin must be one of'):
        cv.model_state_to_msg(ModelState(num_phases=2, segment_origin=7))

    vals = {c: RNG.normal(scale=0.1, size=17) for c in ('err', 'ecc', 'ell')}
    vals['err'][16] = np.nan  # an unmeasured segment stays NaN
    f = Findings(
        phases_used=[0, 3],
        es_phase=3,
        peak=vals,
        peak_unc={c: np.full(17, 0.02) for c in vals},
        es=vals,
        es_unc={c: np.full(17, 0.03) for c in vals},
        function_index=RNG.normal(size=17),
        function_unc=np.full(17, 0.1),
        classes=['normal'] * 6 + ['akinetic', 'dyskinetic'] + ['indeterminate'] * 9,
    )
    m = make_metrics()
    m.update(
        f.message_fields(),
        segment_origin=1,
        segment_origin_confidence=0.0,
        segment_err_unc=np.full(17, 0.05),
        segment_ecc_unc=np.full(17, np.nan),
        segment_ell_unc=np.zeros(0),
    )
    back = cv.msg_to_metrics(cdr(cv.metrics_to_msg(m)))
    for name in FINDING_ARRAY_FIELDS + ('segment_err_unc', 'segment_ecc_unc', 'segment_ell_unc'):
        assert back[name].tobytes() == np.asarray(m[name], np.float64).tobytes(), name
    assert np.isnan(back['finding_peak_err'][16]) and back['findings_es_phase'] == 3
    assert [list(CLASS_CODES)[c] for c in back['segment_class']] == f.classes
    assert back['segment_origin'] == 1
    # Metrics without findings (recorded before them) read as empty / unknown.
    old = cv.msg_to_metrics(cdr(cv.metrics_to_msg(make_metrics())))
    assert (
        old['segment_class'].size == 0
        and old['findings_es_phase'] == -1
        and old['segment_origin'] == 0
    )
    for bad, match in (
        ({'segment_class': np.full(17, 9)}, 'segment_class must hold codes'),
        ({'finding_es_ecc': np.zeros(16)}, '0 or 17'),
        ({'finding_es_ecc': np.full(17, np.inf)}, 'infinite'),
        ({'findings_es_phase': -3}, 'findings_es_phase'),
    ):
        with pytest.raises(ValueError, match=match):
            cv.metrics_to_msg({**m, **bad})


def test_degraded_segments_survive_cdr_and_bad_ones_are_refused():
    """
    Carry the segments a degraded verdict is confined to through ModelState and MotionMetrics.

    Ascending on the way back whatever the order given, empty by default; a number outside 1…17
    or one named twice is refused by name, both ways.
    """
    s = ModelState(num_phases=20, phase_index=8, verdict=1, verdict_reasons='x')
    assert cv.msg_to_model_state(cdr(cv.model_state_to_msg(s))).degraded_segments == ()
    s.degraded_segments = (13, 7, 1)
    msg = cdr(cv.model_state_to_msg(s))
    assert cv.msg_to_model_state(msg).degraded_segments == (1, 7, 13)
    m = make_metrics()
    assert cv.msg_to_metrics(cdr(cv.metrics_to_msg(m)))['degraded_segments'] == ()
    back = cv.msg_to_metrics(cdr(cv.metrics_to_msg({**m, 'degraded_segments': [17, 2]})))
    assert back['degraded_segments'] == (2, 17)
    for bad, match in (((0,), '1..17'), ((18,), '1..17'), ((7.5,), '1..17'), ((7, 7), 'twice')):
        with pytest.raises(ValueError, match=f'degraded_segments .*{match}'):
            cv.model_state_to_msg(ModelState(num_phases=2, degraded_segments=bad))
        with pytest.raises(ValueError, match=f'degraded_segments .*{match}'):
            cv.metrics_to_msg({**m, 'degraded_segments': bad})
    msg.degraded_segments = array.array('B', [7, 99])  # as a foreign publisher might send it
    with pytest.raises(ValueError, match='1..17'):
        cv.msg_to_model_state(msg)


def test_tag_evidence_survives_cdr_and_bad_arrays_are_refused():
    """
    Carry the tag tracks' segment Ecc and its uncertainty through ModelState and MotionMetrics.

    NaN (no evidence) survives; none (empty, the default) goes out as 17 NaN, since an empty
    float64[] ending a message is padded by rmw_fastrtps beyond what rosbags reads; a length other
    than 0 / 17, an infinite value or a negative uncertainty is refused by name, both ways.
    """
    s = ModelState(num_phases=20, phase_index=8)
    back = cv.msg_to_model_state(cdr(cv.model_state_to_msg(s)))
    assert back.tag_ecc.size == back.tag_ecc_unc.size == 17
    assert np.isnan(back.tag_ecc).all() and np.isnan(back.tag_ecc_unc).all()
    s.tag_ecc = np.linspace(-0.2, 0.05, 17)
    s.tag_ecc[16] = np.nan
    s.tag_ecc_unc = np.full(17, 0.03)
    msg = cdr(cv.model_state_to_msg(s))
    back = cv.msg_to_model_state(msg)
    np.testing.assert_array_equal(back.tag_ecc, s.tag_ecc)
    np.testing.assert_array_equal(back.tag_ecc_unc, s.tag_ecc_unc)
    m = {**make_metrics(), 'segment_tag_ecc': s.tag_ecc, 'segment_tag_ecc_unc': s.tag_ecc_unc}
    out = cv.msg_to_metrics(cdr(cv.metrics_to_msg(m)))
    np.testing.assert_array_equal(out['segment_tag_ecc'], s.tag_ecc)
    for name, bad, match in (
        ('tag_ecc', np.zeros(5), '0 or 17'),
        ('tag_ecc', np.full(17, np.inf), 'infinite'),
        ('tag_ecc_unc', np.full(17, -0.1), 'non-negative'),
    ):
        with pytest.raises(ValueError, match=f'{name} .*{match}|{name} holds an {match}'):
            cv.model_state_to_msg(ModelState(num_phases=2, **{name: bad}))
    msg.tag_ecc = array.array('d', [0.1] * 3)  # as a foreign publisher might send it
    with pytest.raises(ValueError, match='tag_ecc must have 0 or 17'):
        cv.msg_to_model_state(msg)

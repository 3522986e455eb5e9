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
numpy ⇄ ROS messages: the only module where arrays meet messages.

Every converter validates what it reads and raises ``ValueError`` naming the problem (wrong
encoding, step/size mismatch, missing fields, inconsistent array lengths, non-finite values where
the message forbids them). Large payloads use the fast paths: ``bytes``/``array.array`` built from
the array's buffer on the way out, ``np.frombuffer`` on the way in (assigning a numpy array to a
``uint8[]`` field element by element is about 100× slower).
"""

from __future__ import annotations

import array
import sys
from typing import Iterable, Mapping

from builtin_interfaces.msg import Time
from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_msgs.msg import MotionMetrics as MotionMetricsMsg
from mlv_msgs.msg import SliceGeometry as SliceGeometryMsg
from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros.core.analysis import metrics as metrics_fields
from mlv_ros.core.analysis.findings import CLASS_CODES
from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import (
    Frame,
    ModelState,
    RegisteredModel,
    SEGMENT_ORIGIN_CODES,
    TagPointSet,
    TAGS_GRID,
    TAGS_LINE_PAIR,
    TAGS_LINES,
    VIEW_LA,
    VIEW_SA,
)
from mlv_ros.core.verdict import checked_level
import numpy as np
from sensor_msgs.msg import Image, PointCloud2, PointField
from std_msgs.msg import Header

PATIENT_FRAME = 'patient'
_HOST_BIG_ENDIAN = sys.byteorder == 'big'

# Image encodings we read and write (sensor_msgs/image_encodings.hpp names).
IMAGE_ENCODINGS = {
    'mono8': np.dtype(np.uint8),
    'mono16': np.dtype(np.uint16),
    '16UC1': np.dtype(np.uint16),
    '32FC1': np.dtype(np.float32),
}
_DTYPE_TO_ENCODING = {
    np.dtype(np.uint8): 'mono8',
    np.dtype(np.uint16): 'mono16',
    np.dtype(np.float32): '32FC1',
}

# PointField datatypes (sensor_msgs/PointField constants) ⇄ numpy dtypes.
_POINTFIELD_DTYPES = {
    PointField.INT8: np.dtype(np.int8),
    PointField.UINT8: np.dtype(np.uint8),
    PointField.INT16: np.dtype(np.int16),
    PointField.UINT16: np.dtype(np.uint16),
    PointField.INT32: np.dtype(np.int32),
    PointField.UINT32: np.dtype(np.uint32),
    PointField.FLOAT32: np.dtype(np.float32),
    PointField.FLOAT64: np.dtype(np.float64),
}
_DTYPE_TO_POINTFIELD = {v: k for k, v in _POINTFIELD_DTYPES.items()}

# A tag position may differ from its pixel placed by the slice geometry by float rounding only.
TAG_POSITION_TOL_MM = 1e-3
# Longest study id accepted (a DICOM UID has at most 64 characters; our hashes are shorter).
MAX_STUDY_ID = 128


# --------------------------------------------------------------------------- time / header
def to_time(seconds: float) -> Time:
    """Float seconds → ``builtin_interfaces/Time`` (nanosecond resolution)."""
    if not np.isfinite(seconds) or seconds < 0:
        raise ValueError(f'stamp must be a finite, non-negative number of seconds, got {seconds}')
    ns = int(round(float(seconds) * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def from_time(t: Time) -> float:
    """``builtin_interfaces/Time`` → float seconds."""
    return t.sec + t.nanosec * 1e-9


def stamp_text(t: Time) -> str:
    """Return a stamp as exact ``sec.nanosec`` text (diagnostics name a bad message by it)."""
    return f'{t.sec}.{t.nanosec:09d}'


def make_header(stamp: float | Time = 0.0, frame_id: str = PATIENT_FRAME) -> Header:
    """Build a ``std_msgs/Header`` in ``frame_id`` at ``stamp`` (seconds or a Time)."""
    return Header(stamp=stamp if isinstance(stamp, Time) else to_time(stamp), frame_id=frame_id)


def _fast_array(typecode: str, values: np.ndarray, dtype) -> array.array:
    """``array.array`` from a numpy array through its buffer (no per-element conversion)."""
    return array.array(typecode, np.ascontiguousarray(values, dtype=dtype).tobytes())


def _require_finite(name: str, values: np.ndarray) -> None:
    bad = np.size(values) - int(np.count_nonzero(np.isfinite(values)))
    if bad:
        raise ValueError(f'{name} has {bad} non-finite value(s) (NaN/inf)')


# --------------------------------------------------------------------------- Image
def image_to_msg(
    image: np.ndarray, header: Header | None = None, encoding: str | None = None
) -> Image:
    """
    Convert a numpy image to ``sensor_msgs/Image``.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        uint8 (``mono8``), uint16 (``mono16``) or float32 (``32FC1``).
    header : Header, optional
        The message's header (stamp and frame); an empty ``Header()`` if omitted.
    encoding : str, optional
        Override the encoding chosen from the dtype (must match the dtype's size and kind).

    Returns
    -------
    Image
        Tightly packed (``step = cols · itemsize``), host byte order flagged in ``is_bigendian``.

    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError(f'image must be 2-D (rows, cols), got shape {image.shape}')
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f'image is empty: shape {image.shape}')
    if encoding is None:
        encoding = _DTYPE_TO_ENCODING.get(image.dtype)
        if encoding is None:
            raise ValueError(
                f'no image encoding for dtype {image.dtype}; use uint8, uint16 or float32'
            )
    elif encoding not in IMAGE_ENCODINGS:
        raise ValueError(
            f'unsupported image encoding {encoding!r}; supported: {sorted(IMAGE_ENCODINGS)}'
        )
    elif IMAGE_ENCODINGS[encoding] != image.dtype:
        raise ValueError(
            f'encoding {encoding!r} needs dtype {IMAGE_ENCODINGS[encoding]}, got {image.dtype}'
        )
    msg = Image(
        header=header or Header(), height=image.shape[0], width=image.shape[1], encoding=encoding
    )
    msg.is_bigendian = int(_HOST_BIG_ENDIAN)
    msg.step = image.shape[1] * image.dtype.itemsize
    msg.data = np.ascontiguousarray(image).tobytes()
    return msg


def msg_to_image(msg: Image, allow_nonfinite: bool = False) -> np.ndarray:
    """
    ``sensor_msgs/Image`` → numpy array, shape (height, width).

    Honours ``step`` padding and ``is_bigendian``. The result may share memory with the message.

    Raises
    ------
    ValueError
        Unsupported encoding, zero size, ``step`` smaller than a row, data length different from
        ``height · step``, or (float images, unless ``allow_nonfinite``) NaN/inf pixels.

    """
    dtype = IMAGE_ENCODINGS.get(msg.encoding)
    if dtype is None:
        raise ValueError(
            f'unsupported image encoding {msg.encoding!r}; supported: {sorted(IMAGE_ENCODINGS)}'
        )
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise ValueError(f'image has zero size ({h}×{w})')
    row_bytes = w * dtype.itemsize
    if step < row_bytes:
        raise ValueError(f'image step {step} is smaller than width·bytes-per-pixel = {row_bytes}')
    if step % dtype.itemsize:
        raise ValueError(f'image step {step} is not a multiple of the pixel size {dtype.itemsize}')
    if len(msg.data) != h * step:
        raise ValueError(
            f'image data has {len(msg.data)} bytes, expected height·step = {h * step}'
        )
    if msg.is_bigendian not in (0, 1):
        raise ValueError(f'image is_bigendian must be 0 or 1, got {msg.is_bigendian}')
    if msg.is_bigendian:
        dtype = dtype.newbyteorder('>')
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    img = np.lib.stride_tricks.as_strided(
        buf.view(dtype), shape=(h, w), strides=(step, dtype.itemsize)
    )
    if msg.is_bigendian != int(_HOST_BIG_ENDIAN):
        img = img.astype(dtype.newbyteorder('='))
    elif step != row_bytes:
        img = np.ascontiguousarray(img)
    if img.dtype.kind == 'f' and not allow_nonfinite:
        _require_finite('image', img)
    return img


# --------------------------------------------------------------------------- PointCloud2
def cloud_to_msg(
    points: np.ndarray | Mapping[str, np.ndarray], header: Header | None = None
) -> PointCloud2:
    """
    Structured array (or mapping name → 1-D array) → ``sensor_msgs/PointCloud2``.

    Parameters
    ----------
    points : structured ndarray, shape (N,), or mapping of equal-length 1-D arrays
        One named scalar field per point channel (e.g. ``x, y, z, dx, dy, dz``), any
        PointField-representable dtype; float fields must be finite (``is_dense`` is true).
    header : Header, optional
        The message's header (stamp and frame); an empty ``Header()`` if omitted.

    Returns
    -------
    PointCloud2
        ``height = 1``, ``width = N``, ``point_step`` = record size, little-endian on x86.

    """
    if isinstance(points, Mapping):
        points = structured(points)
    points = np.asarray(points)
    if points.dtype.names is None:
        raise ValueError('point cloud must be a structured array with named fields')
    if points.ndim != 1:
        raise ValueError(f'point cloud must be 1-D (N,), got shape {points.shape}')
    fields = []
    for name in points.dtype.names:
        fdt, offset = points.dtype.fields[name][:2]
        if fdt.shape:
            raise ValueError(
                f'field {name!r} has sub-array shape {fdt.shape}; use one scalar field per channel'
            )
        datatype = _DTYPE_TO_POINTFIELD.get(fdt.newbyteorder('='))
        if datatype is None:
            raise ValueError(f'field {name!r} has dtype {fdt}, which PointField cannot represent')
        if fdt.kind == 'f':
            _require_finite(f'point field {name!r}', points[name])
        fields.append(PointField(name=name, offset=offset, datatype=datatype, count=1))
    n = points.shape[0]
    msg = PointCloud2(header=header or Header(), height=1, width=n, fields=fields)
    msg.is_bigendian = int(_HOST_BIG_ENDIAN)
    msg.point_step = points.dtype.itemsize
    msg.row_step = n * points.dtype.itemsize
    msg.is_dense = True
    msg.data = np.ascontiguousarray(points).tobytes()
    return msg


def msg_to_cloud(
    msg: PointCloud2, required: Iterable[str] = (), finite: Iterable[str] = ()
) -> np.ndarray:
    """
    ``sensor_msgs/PointCloud2`` → structured array, shape (height·width,).

    Parameters
    ----------
    msg : PointCloud2
        The cloud to unpack: scalar fields (``count`` 1) of PointField datatypes, ``data`` of
        ``row_step · height`` bytes.
    required : iterable of str
        Field names that must be present (e.g. ``("x", "y", "z")``).
    finite : iterable of str
        Field names that must be present, floating point (FLOAT32/FLOAT64) and finite
        (positions: an integer or NaN coordinate is garbage, not a point).

    Raises
    ------
    ValueError
        Missing required fields, unknown datatypes, ``count != 1``, overlapping or out-of-record
        fields, ``data`` whose length differs from ``row_step · height``, or a ``finite`` field
        that is not floating point or holds NaN/inf.

    """
    names = [f.name for f in msg.fields]
    finite = tuple(finite)
    missing = [r for r in (*required, *finite) if r not in names]
    if missing:
        raise ValueError(f'point cloud lacks field(s) {missing}; has {names}')
    if len(set(names)) != len(names):
        raise ValueError(f'point cloud has duplicate field names: {names}')
    point_step, width, height = int(msg.point_step), int(msg.width), int(msg.height)
    spec = {'names': [], 'formats': [], 'offsets': [], 'itemsize': point_step}
    order = '>' if msg.is_bigendian else '<'
    for f in msg.fields:
        dt = _POINTFIELD_DTYPES.get(f.datatype)
        if dt is None:
            raise ValueError(f'field {f.name!r} has unknown PointField datatype {f.datatype}')
        if f.count != 1:
            raise ValueError(
                f'field {f.name!r} has count {f.count}; only scalar fields are supported'
            )
        if f.offset + dt.itemsize > point_step:
            raise ValueError(
                f'field {f.name!r} (offset {f.offset}) does not fit in point_step {point_step}'
            )
        spec['names'].append(f.name)
        spec['formats'].append(dt.newbyteorder(order))
        spec['offsets'].append(f.offset)
    # numpy accepts overlapping fields (aliased bytes): refuse them here.
    spans = sorted(
        (f.offset, f.offset + _POINTFIELD_DTYPES[f.datatype].itemsize, f.name) for f in msg.fields
    )
    for (_, end, a), (start, _, b) in zip(spans, spans[1:]):
        if start < end:
            raise ValueError(f'point cloud fields {a!r} and {b!r} overlap')
    try:
        dtype = np.dtype(spec)
    except ValueError as exc:
        raise ValueError(f'point cloud fields are malformed: {exc}') from None
    if int(msg.row_step) < width * point_step:
        raise ValueError(
            f'row_step {msg.row_step} is smaller than width·point_step = {width * point_step}'
        )
    if len(msg.data) != int(msg.row_step) * height:
        raise ValueError(
            f'point cloud data has {len(msg.data)} bytes, expected row_step·height = '
            f'{msg.row_step * height}'
        )
    buf = np.frombuffer(msg.data, dtype=np.uint8).reshape(height, int(msg.row_step))[
        :, :width * point_step
    ]
    pts = np.ascontiguousarray(buf).view(dtype).reshape(-1)
    if msg.is_bigendian != int(_HOST_BIG_ENDIAN):
        pts = pts.astype(pts.dtype.newbyteorder('='))
    for name in finite:
        if pts.dtype[name].kind != 'f':
            raise ValueError(
                f'point field {name!r} must be FLOAT32 or FLOAT64, got {pts.dtype[name]}'
            )
        _require_finite(f'point field {name!r}', pts[name])
    return pts


def structured(columns: Mapping[str, np.ndarray], dtype=np.float32) -> np.ndarray:
    """Pack a mapping name → 1-D array (all length N) into a structured array of ``dtype``."""
    if not columns:
        raise ValueError('no columns given for the point cloud')
    lengths = {k: np.shape(v) for k, v in columns.items()}
    n = {s[0] if len(s) == 1 else None for s in lengths.values()}
    if len(n) != 1 or None in n:
        raise ValueError(f'point cloud columns must be 1-D of equal length, got shapes {lengths}')
    out = np.empty(n.pop(), dtype=[(k, dtype) for k in columns])
    for k, v in columns.items():
        out[k] = v
    return out


def xyz(points: np.ndarray, names: tuple[str, str, str] = ('x', 'y', 'z')) -> np.ndarray:
    """Three fields of a structured point array as a float64 (N, 3) array."""
    return np.stack([points[n].astype(np.float64) for n in names], axis=-1)


# --------------------------------------------------------------------------- point cloud schemas
# The registered ED model's cloud (/mlv/registered_cloud, float64): each particle's position (mm),
# polar model coordinates (α, β rad, w) and transmural depth (0 endo → 1 epi).
REGISTERED_CLOUD_FIELDS = ('x', 'y', 'z', 'alpha', 'beta', 'w', 'transmural')
# What its consumers need of it (finite, floating point); ``transmural`` is optional.
REGISTERED_REQUIRED_FIELDS = REGISTERED_CLOUD_FIELDS[:6]
# One phase's motion (/lv/motion, float32): position (mm), displacement from ED (mm) and the
# Green–Lagrange strain relative to ED in the radial / circumferential / longitudinal frame.
MOTION_FIELDS = ('x', 'y', 'z', 'dx', 'dy', 'dz', 'err', 'ecc', 'ell')


def registered_to_msgs(
    model: RegisteredModel, stamp: float | Time = 0.0
) -> tuple[PointCloud2, ModelStateMsg]:
    """
    Return the registered model as its cloud and model state, both stamped ``stamp``.

    Parameters
    ----------
    model : RegisteredModel
        The model; a missing ``transmural`` is sent as zeros.
    stamp : float or Time
        The header stamp both carry (what pairs them), s.

    Returns
    -------
    (PointCloud2, ModelState message)
        The cloud of :data:`REGISTERED_CLOUD_FIELDS` (float64) and the state.

    """
    n = len(model)
    transmural = np.zeros(n) if model.transmural is None else model.transmural
    columns = dict(zip(REGISTERED_CLOUD_FIELDS, (*model.positions.T, *model.polar, transmural)))
    cloud = cloud_to_msg(structured(columns, np.float64), make_header(stamp))
    return cloud, model_state_to_msg(model.state, stamp)


def msg_to_registered_cloud(msg: PointCloud2) -> np.ndarray:
    """
    Unpack a registered cloud, checking what its consumers need of it.

    Parameters
    ----------
    msg : PointCloud2
        A ``/mlv/registered_cloud`` message.

    Returns
    -------
    ndarray
        Its structured array (:func:`msg_to_cloud`).

    Raises
    ------
    ValueError
        A field of :data:`REGISTERED_REQUIRED_FIELDS` missing, not floating point or not finite
        (and whatever :func:`msg_to_cloud` refuses).

    """
    return msg_to_cloud(msg, finite=REGISTERED_REQUIRED_FIELDS)


def registered_model(cloud: np.ndarray, state: ModelState) -> RegisteredModel:
    """
    Return the registered model from its unpacked cloud and its state.

    Parameters
    ----------
    cloud : ndarray
        :func:`msg_to_registered_cloud` of the cloud.
    state : ModelState
        The registered state of the same stamp.

    Returns
    -------
    RegisteredModel
        Positions as float64 (N, 3); the other columns as the cloud holds them.

    """
    transmural = cloud['transmural'] if 'transmural' in cloud.dtype.names else None
    return RegisteredModel(
        xyz(cloud), cloud['alpha'], cloud['beta'], cloud['w'], state, transmural
    )


def motion_to_msg(
    positions: np.ndarray, rest: np.ndarray, strain: Mapping, stamp: float | Time = 0.0
) -> PointCloud2:
    """
    Return one phase's motion as a ``/lv/motion`` cloud (:data:`MOTION_FIELDS`, float32).

    Parameters
    ----------
    positions : ndarray, shape (N, 3)
        Particle positions at the phase, mm (patient).
    rest : ndarray, shape (N, 3)
        The same particles at ED, mm.
    strain : mapping
        ``rr``, ``cc``, ``ll``: Green–Lagrange strain relative to ED, each shape (N,).
    stamp : float or Time
        Header stamp (the phase's model state carries the same), s.

    Returns
    -------
    PointCloud2
        The cloud.

    """
    d = np.asarray(positions) - np.asarray(rest)
    columns = (*np.asarray(positions).T, *d.T, strain['rr'], strain['cc'], strain['ll'])
    return cloud_to_msg(structured(dict(zip(MOTION_FIELDS, columns))), make_header(stamp))


# --------------------------------------------------------------------------- custom messages
def geometry_to_msg(geometry: SliceGeometry) -> SliceGeometryMsg:
    """:class:`SliceGeometry` → ``mlv_msgs/SliceGeometry``."""
    return SliceGeometryMsg(
        image_position=geometry.image_position,
        row_direction=geometry.row_direction,
        column_direction=geometry.column_direction,
        row_spacing=geometry.row_spacing,
        column_spacing=geometry.column_spacing,
        slice_thickness=geometry.slice_thickness,
    )


def msg_to_geometry(msg: SliceGeometryMsg) -> SliceGeometry:
    """Convert ``mlv_msgs/SliceGeometry`` to :class:`SliceGeometry` (unit, orthogonal, > 0)."""
    return SliceGeometry(
        image_position=np.array(msg.image_position),
        row_direction=np.array(msg.row_direction),
        column_direction=np.array(msg.column_direction),
        row_spacing=msg.row_spacing,
        column_spacing=msg.column_spacing,
        slice_thickness=msg.slice_thickness,
    )


def _check_view(view: int) -> int:
    if view not in (VIEW_SA, VIEW_LA):
        raise ValueError(f'view must be VIEW_SA ({VIEW_SA}) or VIEW_LA ({VIEW_LA}), got {view}')
    return int(view)


def _check_phase(phase_index: int, num_phases: int) -> None:
    if num_phases < 1:
        raise ValueError(f'num_phases must be ≥ 1, got {num_phases}')
    if not 0 <= phase_index < num_phases:
        raise ValueError(f'phase_index {phase_index} outside [0, {num_phases})')


def _check_slice(view: int, slice_index: int, num_sa_slices: int, num_la_slices: int) -> None:
    """Check a slice index lies within its view's declared slice count (0 = count unknown)."""
    count, name = (
        (num_sa_slices, 'num_sa_slices') if view == VIEW_SA else (num_la_slices, 'num_la_slices')
    )
    if count and not 0 <= slice_index < count:
        raise ValueError(
            f'slice_index {slice_index} outside [0, {name} = {count}) for view {view}'
        )


def _check_study_id(study_id, name: str = 'study_id') -> str:
    """
    Check a message's ``study_id`` (or ``run_id``, by ``name``).

    It must be text of printable characters, at most :data:`MAX_STUDY_ID` long (empty = unknown).
    """
    study_id = str(study_id)
    if len(study_id) > MAX_STUDY_ID:
        raise ValueError(f'{name} has {len(study_id)} characters, at most {MAX_STUDY_ID} allowed')
    if not study_id.isprintable():
        raise ValueError(f'{name} {study_id!r} holds non-printable characters')
    return study_id


def frame_to_msg(frame: Frame, stamp: float | Time = 0.0) -> TaggedFrame:
    """:class:`Frame` → ``mlv_msgs/TaggedFrame``; ``stamp`` goes to both headers."""
    _check_view(frame.view)
    _check_phase(frame.phase_index, frame.num_phases)
    _check_slice(frame.view, frame.slice_index, frame.num_sa_slices, frame.num_la_slices)
    header = make_header(stamp)
    return TaggedFrame(
        header=header,
        image=_frame_image_to_msg(frame, header),
        geometry=geometry_to_msg(frame.geometry),
        view=frame.view,
        slice_index=frame.slice_index,
        phase_index=frame.phase_index,
        num_phases=frame.num_phases,
        trigger_time=float(frame.trigger_time),
        cycle_duration=float(frame.cycle_duration),
        series_uid=frame.series_uid,
        num_sa_slices=frame.num_sa_slices,
        num_la_slices=frame.num_la_slices,
        study_id=_check_study_id(frame.study_id),
        run_id=_check_study_id(frame.run_id, 'run_id'),
        tag_lines=_check_tag_lines(frame.tag_lines),
    )


# Two single-line series of one slice (TAGS_LINE_PAIR) travel as one two-channel image.
LINE_PAIR_ENCODINGS = {'8UC2': 'mono8', '16UC2': 'mono16', '32FC2': '32FC1'}


def _check_tag_lines(tag_lines) -> int:
    """Return ``tag_lines`` as an int, or raise ValueError when it is not a TAGS_* value."""
    if tag_lines not in (TAGS_GRID, TAGS_LINES, TAGS_LINE_PAIR):
        raise ValueError(
            f'tag_lines must be {TAGS_GRID} (grid), {TAGS_LINES} (one family of tag lines) or '
            f'{TAGS_LINE_PAIR} (two single-line series), got {tag_lines!r}'
        )
    return int(tag_lines)


def _frame_image_to_msg(frame: Frame, header: Header) -> Image:
    """Return the frame's image message: two channels (image, line_image) for a line pair."""
    if _check_tag_lines(frame.tag_lines) != TAGS_LINE_PAIR:
        return image_to_msg(frame.image, header=header)
    a, b = np.asarray(frame.image), np.asarray(frame.line_image)
    if frame.line_image is None or a.shape != b.shape or a.dtype != b.dtype:
        raise ValueError(
            'a line-pair frame needs line_image of the shape and dtype of image, got '
            f'{None if frame.line_image is None else (b.shape, b.dtype)} for {(a.shape, a.dtype)}'
        )
    msg = image_to_msg(np.concatenate([a, b], axis=1), header=header)  # validates a and b
    msg.width //= 2
    msg.encoding = {v: k for k, v in LINE_PAIR_ENCODINGS.items()}[msg.encoding]
    msg.data = np.ascontiguousarray(np.stack([a, b], axis=-1)).tobytes()
    return msg


def _msg_to_frame_images(msg: TaggedFrame, allow_nonfinite: bool):
    """Return ``(image, line_image)`` of a frame message (``line_image`` None unless a pair)."""
    pair = _check_tag_lines(msg.tag_lines) == TAGS_LINE_PAIR
    im = msg.image
    if (im.encoding in LINE_PAIR_ENCODINGS) != pair:
        raise ValueError(
            f'image encoding {im.encoding!r} does not fit tag_lines {msg.tag_lines} (a line '
            f'pair has two channels, {"/".join(LINE_PAIR_ENCODINGS)}; every other frame one)'
        )
    if not pair:
        return msg_to_image(im, allow_nonfinite=allow_nonfinite), None
    # The two interleaved channels read as one image twice as wide, then split.
    wide = Image(
        height=im.height, width=2 * im.width, step=im.step, is_bigendian=im.is_bigendian,
        encoding=LINE_PAIR_ENCODINGS[im.encoding],
    )
    wide.data = im.data
    both = msg_to_image(wide, allow_nonfinite=allow_nonfinite).reshape(im.height, im.width, 2)
    return np.ascontiguousarray(both[..., 0]), np.ascontiguousarray(both[..., 1])


def msg_to_frame(msg: TaggedFrame, allow_nonfinite: bool = False) -> Frame:
    """``mlv_msgs/TaggedFrame`` → :class:`Frame` (image, geometry, indices validated)."""
    _check_view(msg.view)
    _check_phase(msg.phase_index, msg.num_phases)
    _check_slice(msg.view, msg.slice_index, msg.num_sa_slices, msg.num_la_slices)
    image, line_image = _msg_to_frame_images(msg, allow_nonfinite)
    return Frame(
        image=image,
        geometry=msg_to_geometry(msg.geometry),
        view=msg.view,
        slice_index=msg.slice_index,
        phase_index=msg.phase_index,
        num_phases=msg.num_phases,
        trigger_time=msg.trigger_time,
        cycle_duration=msg.cycle_duration,
        series_uid=msg.series_uid,
        num_sa_slices=msg.num_sa_slices,
        num_la_slices=msg.num_la_slices,
        study_id=_check_study_id(msg.study_id),
        run_id=_check_study_id(msg.run_id, 'run_id'),
        tag_lines=int(msg.tag_lines),
        line_image=line_image,
    )


def tagpoints_to_msg(points: TagPointSet, stamp: float | Time | None = None) -> TagPoints:
    """:class:`TagPointSet` → ``mlv_msgs/TagPoints`` (per-point arrays flattened row-major)."""
    n = len(points)
    rc = np.asarray(points.pixel_rc, dtype=np.float64).reshape(-1, 2)
    pos = np.asarray(points.position, dtype=np.float64).reshape(-1, 3)
    conf = np.asarray(points.confidence, dtype=np.float32).reshape(-1)
    if not (rc.shape[0] == pos.shape[0] == conf.shape[0] == n):
        raise ValueError(
            f'tag point arrays disagree: pixel_rc {rc.shape[0]}, position {pos.shape[0]}, '
            f'track_id {n}, confidence {conf.shape[0]}'
        )
    _require_finite('tag pixel_rc', rc)
    _require_finite('tag position', pos)
    _require_finite('tag confidence', conf)
    line = _checked_line_normals(points.line_normal, n)
    _check_view(points.view)
    _check_phase(points.phase_index, points.num_phases)
    _check_slice(points.view, points.slice_index, points.num_sa_slices, points.num_la_slices)
    return TagPoints(
        header=make_header(points.stamp if stamp is None else stamp),
        view=points.view,
        slice_index=points.slice_index,
        phase_index=points.phase_index,
        num_phases=points.num_phases,
        num_sa_slices=points.num_sa_slices,
        num_la_slices=points.num_la_slices,
        geometry=geometry_to_msg(points.geometry),
        pixel_rc=_fast_array('d', rc, np.float64),
        position=_fast_array('d', pos, np.float64),
        track_id=_fast_array('i', np.asarray(points.track_id).reshape(-1), np.int32),
        confidence=_fast_array('f', conf, np.float32),
        status=points.status,
        study_id=_check_study_id(points.study_id),
        run_id=_check_study_id(points.run_id, 'run_id'),
        line_normal=_fast_array('f', line, np.float32),
    )


def _checked_line_normals(line_normal, n: int) -> np.ndarray:
    """
    Return tag-line normals as (N, 3) or (0, 3) float64, or raise ValueError.

    Empty (grid intersections) or one per point: a unit vector (within 1e-3: the message carries
    float32), or a row of NaN (that point is an intersection).
    """
    line = np.asarray(line_normal, dtype=np.float64)
    if line.size == 0:
        return np.zeros((0, 3))
    if line.size != 3 * n:
        raise ValueError(
            f'tag line_normal has {line.size} values, want 0 or {3 * n} (3 per point)'
        )
    line = line.reshape(n, 3)
    grid = np.isnan(line).all(axis=1)
    rows = line[~grid]
    if not np.all(np.isfinite(rows)) or np.any(np.abs(np.linalg.norm(rows, axis=1) - 1) > 1e-3):
        raise ValueError('tag line_normal rows must be unit vectors or all NaN (an intersection)')
    return line


def msg_to_tagpoints(msg: TagPoints) -> TagPointSet:
    """
    ``mlv_msgs/TagPoints`` → :class:`TagPointSet`.

    Array lengths must agree (2N, 3N, N, N), values be finite, confidences lie in [0, 1], and each
    position be its ``pixel_rc`` placed by ``geometry`` (within ``TAG_POSITION_TOL_MM``): a point
    off its own slice plane is garbage, not a measurement. ``line_normal`` is empty (grid
    intersections; recordings made before the field) or 3N unit vectors / NaN rows.
    """
    n = len(msg.track_id)
    if len(msg.pixel_rc) != 2 * n or len(msg.position) != 3 * n or len(msg.confidence) != n:
        raise ValueError(
            f'TagPoints arrays disagree: track_id {n}, pixel_rc {len(msg.pixel_rc)} (want '
            f'{2 * n}), '
            f'position {len(msg.position)} (want {3 * n}), confidence {len(msg.confidence)} '
            f'(want {n})'
        )
    _check_view(msg.view)
    _check_phase(msg.phase_index, msg.num_phases)
    _check_slice(msg.view, msg.slice_index, msg.num_sa_slices, msg.num_la_slices)
    geometry = msg_to_geometry(msg.geometry)
    rc = np.frombuffer(msg.pixel_rc, dtype=np.float64).reshape(n, 2).copy()
    pos = np.frombuffer(msg.position, dtype=np.float64).reshape(n, 3).copy()
    conf = np.frombuffer(msg.confidence, dtype=np.float32).copy()
    _require_finite('tag pixel_rc', rc)
    _require_finite('tag position', pos)
    _require_finite('tag confidence', conf)
    if n and (conf.min() < 0 or conf.max() > 1):
        raise ValueError(
            f'tag confidence must lie in [0, 1], got [{conf.min():g}, {conf.max():g}]'
        )
    off = np.linalg.norm(pos - geometry.pixel_to_patient(rc), axis=1) if n else np.zeros(0)
    if np.any(off > TAG_POSITION_TOL_MM):
        raise ValueError(
            f'{int(np.count_nonzero(off > TAG_POSITION_TOL_MM))} tag position(s) disagree with '
            f'pixel_rc placed by the geometry (up to {off.max():.3g} mm off)'
        )
    return TagPointSet(
        view=msg.view,
        slice_index=msg.slice_index,
        phase_index=msg.phase_index,
        num_phases=msg.num_phases,
        geometry=geometry,
        pixel_rc=rc,
        position=pos,
        track_id=np.frombuffer(msg.track_id, dtype=np.int32).copy(),
        confidence=conf,
        status=msg.status,
        stamp=from_time(msg.header.stamp),
        num_sa_slices=msg.num_sa_slices,
        num_la_slices=msg.num_la_slices,
        study_id=_check_study_id(msg.study_id),
        run_id=_check_study_id(msg.run_id, 'run_id'),
        line_normal=_checked_line_normals(
            np.frombuffer(msg.line_normal, dtype=np.float32), n
        ),
    )


def model_state_to_msg(state: ModelState, stamp: float | Time = 0.0) -> ModelStateMsg:
    """:class:`ModelState` → ``mlv_msgs/ModelState`` (all parameters must be finite)."""
    q = np.asarray(state.rotation, dtype=np.float64).reshape(-1)
    c = np.asarray(state.translation, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or c.shape != (3,):
        raise ValueError(
            f'model state needs translation (3,) and rotation quaternion (4,), got {c.shape}, '
            f'{q.shape}'
        )
    scalars = np.array(
        [state.a0, state.a1, state.a2, state.a3, state.tau, state.residual], dtype=np.float64
    )
    _require_finite('model state', np.concatenate([q, c, scalars]))
    if abs(np.linalg.norm(q) - 1.0) > 1e-6:
        raise ValueError(
            f'model rotation must be a unit quaternion (norm {np.linalg.norm(q):.6g})'
        )
    _check_phase(state.phase_index, state.num_phases)
    return ModelStateMsg(
        header=make_header(stamp),
        phase_index=state.phase_index,
        num_phases=state.num_phases,
        translation=c,
        rotation=q,
        a0=float(state.a0),
        a1=float(state.a1),
        a2=float(state.a2),
        a3=float(state.a3),
        tau=float(state.tau),
        iterations=int(state.iterations),
        residual=float(state.residual),
        converged=bool(state.converged),
        num_particles=int(state.num_particles),
        num_control_points=int(state.num_control_points),
        verdict=checked_level(state.verdict),
        verdict_reasons=str(state.verdict_reasons),
        study_id=_check_study_id(state.study_id),
        run_id=_check_study_id(state.run_id, 'run_id'),
        segment_origin=_check_origin(getattr(state, 'segment_origin', 0)),
        segment_origin_confidence=_check_confidence(
            getattr(state, 'segment_origin_confidence', 0.0)
        ),
        degraded_segments=_fast_array(
            'B', _check_segments(getattr(state, 'degraded_segments', ())), np.uint8
        ),
        **{
            name: _fast_array('d', _on_the_wire(_check_tag_evidence(state, name)), np.float64)
            for name in TAG_EVIDENCE_FIELDS
        },
    )


#: ModelState's per-segment tag evidence (17 or empty, NaN allowed; uncertainties ≥ 0).
TAG_EVIDENCE_FIELDS = ('tag_ecc', 'tag_ecc_unc')


def _on_the_wire(v: np.ndarray) -> np.ndarray:
    """
    Return per-segment tag evidence as sent: 17 NaN (no evidence) in place of none.

    The evidence arrays end ModelState and MotionMetrics. rmw_fastrtps pads an empty float64[]
    as if it held an 8-aligned element, so a message ending with one carries 4 bytes more than
    its CDR says, which rosbags (an independent reader of our recordings) refuses; 17 NaN read
    the same as empty everywhere here (no segment has evidence).
    """
    return v if v.size else np.full(17, np.nan)


def _check_tag_evidence(source, name: str) -> np.ndarray:
    """
    Return ``source.name`` (a ModelState or its message) as a checked float array.

    Raises
    ------
    ValueError
        Not 0 or 17 entries, an infinite value, or a negative uncertainty.

    """
    v = np.asarray(getattr(source, name, ()), dtype=np.float64).reshape(-1)
    _check_segment_extra(name, v)
    if name.endswith('_unc') and np.any(v < 0):
        raise ValueError(f'{name} must hold non-negative uncertainties, got {v.tolist()}')
    return v


def _check_origin(v) -> int:
    """Check a ``segment_origin`` code (:data:`~mlv_ros.core.types.SEGMENT_ORIGIN_CODES`)."""
    if isinstance(v, bool) or int(v) != v or int(v) not in SEGMENT_ORIGIN_CODES.values():
        raise ValueError(
            f'segment_origin must be one of {sorted(SEGMENT_ORIGIN_CODES.values())} '
            f'({", ".join(f"{c} {n}" for n, c in SEGMENT_ORIGIN_CODES.items())}), got {v!r}'
        )
    return int(v)


def _check_segments(v, name: str = 'degraded_segments') -> tuple:
    """
    Check a list of AHA segment numbers: distinct integers 1…17; return them ascending.

    Raises
    ------
    ValueError
        A value that is not an integer in 1…17, or one given twice.

    """
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.size and (
        not np.all(np.isfinite(a)) or np.any(a != np.round(a)) or np.any((a < 1) | (a > 17))
    ):
        raise ValueError(f'{name} must hold AHA segment numbers 1..17, got {a.tolist()}')
    if np.unique(a).size != a.size:
        raise ValueError(f'{name} names a segment twice: {a.astype(int).tolist()}')
    return tuple(sorted(int(x) for x in a))


def _check_confidence(v) -> float:
    v = float(v)
    if not 0.0 <= v <= 1.0:
        raise ValueError(f'segment_origin_confidence must be in [0, 1], got {v}')
    return v


def msg_to_model_state(msg: ModelStateMsg) -> ModelState:
    """``mlv_msgs/ModelState`` → :class:`ModelState` (finite, unit quaternion, phase in range)."""
    state = ModelState(
        phase_index=msg.phase_index,
        num_phases=msg.num_phases,
        translation=np.array(msg.translation),
        rotation=np.array(msg.rotation),
        a0=msg.a0,
        a1=msg.a1,
        a2=msg.a2,
        a3=msg.a3,
        tau=msg.tau,
        iterations=msg.iterations,
        residual=msg.residual,
        converged=msg.converged,
        num_particles=msg.num_particles,
        num_control_points=msg.num_control_points,
        verdict=checked_level(msg.verdict),
        verdict_reasons=msg.verdict_reasons,
        study_id=_check_study_id(msg.study_id),
        run_id=_check_study_id(msg.run_id, 'run_id'),
        segment_origin=_check_origin(msg.segment_origin),
        segment_origin_confidence=_check_confidence(msg.segment_origin_confidence),
        degraded_segments=_check_segments(np.frombuffer(msg.degraded_segments, dtype=np.uint8)),
        **{n: _check_tag_evidence(msg, n).copy() for n in TAG_EVIDENCE_FIELDS},
    )
    _require_finite(
        'model state',
        np.concatenate(
            [
                state.translation,
                state.rotation,
                [state.a0, state.a1, state.a2, state.a3, state.tau, state.residual],
            ]
        ),
    )
    if abs(np.linalg.norm(state.rotation) - 1.0) > 1e-6:
        raise ValueError(
            f'model rotation must be a unit quaternion (norm {np.linalg.norm(state.rotation):.6g})'
        )
    _check_phase(state.phase_index, state.num_phases)
    return state


# MotionMetrics' field groups; the counts and the NaN-allowed segment fields are optional in the
# input (default empty).
METRIC_LEVEL_FIELDS = metrics_fields.LEVEL_FIELDS
METRIC_SCALAR_FIELDS = metrics_fields.SCALAR_FIELDS
METRIC_SEGMENT_FIELDS = metrics_fields.SEGMENT_FIELDS
METRIC_COUNT_FIELDS = metrics_fields.COUNT_FIELDS
METRIC_NAN_SEGMENT_FIELDS = metrics_fields.NAN_SEGMENT_FIELDS


def _metrics_value(metrics, name):
    return metrics[name] if isinstance(metrics, Mapping) else getattr(metrics, name)


def metrics_to_msg(metrics, stamp: float | Time = 0.0) -> MotionMetricsMsg:
    """
    Convert per-phase motion metrics to ``mlv_msgs/MotionMetrics``.

    The metrics are a mapping or object with the MotionMetrics field names. Per-level arrays must
    share one length; segment arrays must be empty or have 17 entries; values must be finite.
    """
    msg = MotionMetricsMsg(header=make_header(stamp))
    msg.phase_index = int(_metrics_value(metrics, 'phase_index'))
    msg.num_phases = int(_metrics_value(metrics, 'num_phases'))
    _check_phase(msg.phase_index, msg.num_phases)
    lengths = set()
    for name in METRIC_LEVEL_FIELDS:
        v = np.asarray(_metrics_value(metrics, name), dtype=np.float64).reshape(-1)
        _require_finite(name, v)
        lengths.add(v.size)
        setattr(msg, name, _fast_array('d', v, np.float64))
    if len(lengths) > 1:
        raise ValueError(f'per-level metric arrays have different lengths: {sorted(lengths)}')
    for name in METRIC_SEGMENT_FIELDS:
        v = np.asarray(_metrics_value(metrics, name), dtype=np.float64).reshape(-1)
        if v.size not in (0, 17):
            raise ValueError(f'{name} must have 0 or 17 (AHA segments) entries, got {v.size}')
        _require_finite(name, v)
        setattr(msg, name, _fast_array('d', v, np.float64))
    for name in METRIC_SCALAR_FIELDS:
        v = float(_metrics_value(metrics, name))
        _require_finite(name, np.array([v]))
        setattr(msg, name, v)
    for name, want in zip(METRIC_COUNT_FIELDS, (lengths.pop() if lengths else 0, 17)):
        try:
            v = np.asarray(_metrics_value(metrics, name)).reshape(-1)
        except (KeyError, AttributeError):
            v = np.zeros(0)
        if v.size not in (0, want):
            raise ValueError(f'{name} must have 0 or {want} entries, got {v.size}')
        if v.size and (np.any(v < 0) or not np.all(np.isfinite(v))):
            raise ValueError(f'{name} must hold non-negative counts')
        setattr(msg, name, _fast_array('I', v, np.uint32))
    for name in METRIC_NAN_SEGMENT_FIELDS + ('segment_class',):
        try:
            v = np.asarray(_metrics_value(metrics, name), dtype=np.float64).reshape(-1)
        except (KeyError, AttributeError):
            v = np.zeros(0)
        _check_segment_extra(name, v)
        if name == 'segment_class':
            msg.segment_class = _fast_array('B', v, np.uint8)
        else:
            if name in ('segment_tag_ecc', 'segment_tag_ecc_unc'):
                v = _on_the_wire(v)
            setattr(msg, name, _fast_array('d', v, np.float64))
    # Optional in the input: metrics without a verdict are ok with no reasons, without a study
    # of no known study, without findings of an unknown segment origin and ES phase.
    for name, default, check in (
        ('verdict', 0, checked_level),
        ('verdict_reasons', '', str),
        ('segment_origin', 0, _check_origin),
        ('segment_origin_confidence', 0.0, _check_confidence),
        ('findings_es_phase', -1, _check_es_phase),
        ('study_id', '', _check_study_id),
        ('run_id', '', lambda v: _check_study_id(v, 'run_id')),
    ):
        try:
            value = _metrics_value(metrics, name)
        except (KeyError, AttributeError):
            value = default
        setattr(msg, name, check(value))
    try:
        segments = _metrics_value(metrics, 'degraded_segments')
    except (KeyError, AttributeError):
        segments = ()
    msg.degraded_segments = _fast_array('B', _check_segments(segments), np.uint8)
    return msg


def _check_segment_extra(name: str, v: np.ndarray) -> None:
    """
    Check findings / uncertainty arrays.

    They must have 0 or 17 entries; classes are codes 0…4; NaN (not measured) is allowed, ±inf is
    not.
    """
    if v.size not in (0, 17):
        raise ValueError(f'{name} must have 0 or 17 (AHA segments) entries, got {v.size}')
    if np.any(np.isinf(v)):
        raise ValueError(f'{name} holds an infinite value')
    if (
        name == 'segment_class'
        and v.size
        and (
            not np.all(np.isfinite(v))
            or np.any(v != np.round(v))
            or np.any((v < 0) | (v >= len(CLASS_CODES)))
        )
    ):
        raise ValueError(
            f'segment_class must hold codes 0..{len(CLASS_CODES) - 1} '
            f'({", ".join(f"{c} {n}" for n, c in CLASS_CODES.items())})'
        )


def _check_es_phase(v) -> int:
    if isinstance(v, bool) or int(v) != v or int(v) < -1:
        raise ValueError(f'findings_es_phase must be a phase index or -1 (none yet), got {v!r}')
    return int(v)


def msg_to_metrics(msg: MotionMetricsMsg) -> dict:
    """``mlv_msgs/MotionMetrics`` → dict of numpy arrays and floats (validated lengths)."""
    out = {
        'phase_index': msg.phase_index,
        'num_phases': msg.num_phases,
        'stamp': from_time(msg.header.stamp),
    }
    lengths = set()
    for name in METRIC_LEVEL_FIELDS:
        out[name] = np.frombuffer(getattr(msg, name), dtype=np.float64).copy()
        lengths.add(out[name].size)
    if len(lengths) > 1:
        raise ValueError(f'per-level metric arrays have different lengths: {sorted(lengths)}')
    for name in METRIC_SEGMENT_FIELDS:
        out[name] = np.frombuffer(getattr(msg, name), dtype=np.float64).copy()
        if out[name].size not in (0, 17):
            raise ValueError(f'{name} must have 0 or 17 entries, got {out[name].size}')
    for name in METRIC_SCALAR_FIELDS:
        out[name] = float(getattr(msg, name))
    for name in METRIC_COUNT_FIELDS:
        out[name] = np.frombuffer(getattr(msg, name), dtype=np.uint32).astype(np.int64)
    for name in METRIC_NAN_SEGMENT_FIELDS:
        out[name] = np.frombuffer(getattr(msg, name), dtype=np.float64).copy()
        _check_segment_extra(name, out[name])
    out['segment_class'] = np.frombuffer(msg.segment_class, dtype=np.uint8).astype(np.int64)
    _check_segment_extra('segment_class', out['segment_class'].astype(np.float64))
    out['segment_origin'] = _check_origin(msg.segment_origin)
    out['segment_origin_confidence'] = _check_confidence(msg.segment_origin_confidence)
    out['findings_es_phase'] = _check_es_phase(msg.findings_es_phase)
    out['verdict'] = checked_level(msg.verdict)
    out['verdict_reasons'] = msg.verdict_reasons
    out['degraded_segments'] = _check_segments(np.frombuffer(msg.degraded_segments, np.uint8))
    out['study_id'] = _check_study_id(msg.study_id)
    out['run_id'] = _check_study_id(msg.run_id, 'run_id')
    return out


# --------------------------------------------------------------------------- Foxglove schemas
# The live view (mlv_ros/nodes/live_view.py) serves the graph's results with Foxglove's own
# schemas (foxglove-sdk; imported here on first use, so the graph runs without it).
FOXGLOVE_CURVE_FIELDS = (
    'cavity_volume_ml',
    'ejection_fraction',
    'twist_apex_deg',
    'twist_base_deg',
    'torsion_deg_per_cm',
)


def foxglove_timestamp(stamp: Time):
    """ROS ``builtin_interfaces/Time`` → ``foxglove.messages.Timestamp`` (same instant)."""
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(stamp.sec), nsec=int(stamp.nanosec))


def cloud_to_foxglove(points: np.ndarray, stamp: Time, frame_id: str = PATIENT_FRAME):
    """
    Structured point array (as :func:`msg_to_cloud` returns it) → ``foxglove.PointCloud``.

    Parameters
    ----------
    points : structured ndarray, shape (N,)
        Scalar numeric fields (e.g. ``x y z`` in mm, ``dx dy dz`` in mm, ``err ecc ell``
        dimensionless); the record layout (offsets, stride) is kept.
    stamp : builtin_interfaces/Time
        The source message's header stamp.
    frame_id : str
        The coordinate frame of ``x y z`` (``patient``: DICOM LPS, mm, as the recorded clouds).

    Returns
    -------
    foxglove.messages.PointCloud
        Identity pose, little-endian packed fields with the same names, offsets and stride.

    Raises
    ------
    ValueError
        Not a 1-D structured array, or a field of a type PackedElementField cannot hold.

    """
    from foxglove.messages import (
        PackedElementField,
        PackedElementFieldNumericType,
        PointCloud,
        Pose,
        Quaternion,
        Vector3,
    )

    points = np.asarray(points)
    if points.dtype.names is None or points.ndim != 1:
        raise ValueError('a Foxglove point cloud needs a 1-D structured array of named fields')
    kinds = {
        np.dtype(np.uint8): 'Uint8',
        np.dtype(np.int8): 'Int8',
        np.dtype(np.uint16): 'Uint16',
        np.dtype(np.int16): 'Int16',
        np.dtype(np.uint32): 'Uint32',
        np.dtype(np.int32): 'Int32',
        np.dtype(np.float32): 'Float32',
        np.dtype(np.float64): 'Float64',
    }
    little = points.dtype.newbyteorder('<')
    fields = []
    for name in points.dtype.names:
        fdt, offset = points.dtype.fields[name][:2]
        kind = kinds.get(fdt.newbyteorder('='))
        if kind is None or fdt.shape:
            raise ValueError(
                f'field {name!r} has dtype {fdt}, which a Foxglove PackedElementField cannot hold'
            )
        fields.append(
            PackedElementField(
                name=name, offset=offset, type=getattr(PackedElementFieldNumericType, kind)
            )
        )
    return PointCloud(
        timestamp=foxglove_timestamp(stamp),
        frame_id=frame_id,
        pose=Pose(
            position=Vector3(x=0.0, y=0.0, z=0.0),
            orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        point_stride=points.dtype.itemsize,
        fields=fields,
        data=points.astype(little).tobytes(),
    )


def display_window(image: np.ndarray) -> tuple[float, float]:
    """
    Grey-level window (low, high) for showing a slice: its 1st and 99.5th percentiles.

    Scale-free (any scanner's stored range, rescale or float image); taken once per slice (from
    its first frame) and kept, so the tags' fading over the cycle stays visible.
    """
    image = np.asarray(image, dtype=np.float64)
    finite = image[np.isfinite(image)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = np.percentile(finite, [1.0, 99.5])
    return float(low), float(high if high > low else low + 1.0)


def image_to_foxglove(
    image: np.ndarray, window: tuple[float, float], stamp: Time, frame_id: str = PATIENT_FRAME
):
    """
    Convert a slice image to ``foxglove.RawImage`` (``mono8``).

    Grey levels are mapped linearly from ``window`` (low → 0, high → 255, clipped; NaN → 0).

    Parameters
    ----------
    image : ndarray, shape (rows, columns)
        Any numeric dtype (the frame as :func:`msg_to_image` gives it).
    window : (float, float)
        Grey levels shown as black and white (:func:`display_window`).
    stamp : builtin_interfaces/Time
        The frame's header stamp (its tag points' annotations carry the same one).
    frame_id : str, optional
        The RawImage's ``frame_id`` (default :data:`PATIENT_FRAME`, ``'patient'``).

    """
    from foxglove.messages import RawImage

    image = np.asarray(image)
    if image.ndim != 2 or not image.size:
        raise ValueError(f'an image to show must be 2-D and not empty, got shape {image.shape}')
    low, high = float(window[0]), float(window[1])
    if not (np.isfinite(low) and np.isfinite(high) and high > low):
        raise ValueError(f'display window must be finite with high > low, got {window}')
    scaled = (np.nan_to_num(image.astype(np.float32), nan=low) - low) * (255.0 / (high - low))
    data = np.clip(scaled, 0.0, 255.0).astype(np.uint8)
    rows, cols = data.shape
    return RawImage(
        timestamp=foxglove_timestamp(stamp),
        frame_id=frame_id,
        width=cols,
        height=rows,
        encoding='mono8',
        step=cols,
        data=data.tobytes(),
    )


def tagpoints_to_foxglove(
    pixel_rc: np.ndarray, stamp: Time, color=(1.0, 0.3, 0.1, 1.0), size_px: float = 4.0
):
    """
    Tag points of one frame → ``foxglove.ImageAnnotations`` (one POINTS annotation).

    Parameters
    ----------
    pixel_rc : ndarray, shape (N, 2)
        (row, column) of each point, pixels, 0 at the centre of the first pixel (as TagPoints).
        Foxglove places annotations from the top-left *corner* of the image, so each point is
        drawn at (column + 0.5, row + 0.5).
    stamp : builtin_interfaces/Time
        The tag points' header stamp (= their frame's), which pairs them with the image.
    color : tuple of 4 floats
        RGBA, 0..1.
    size_px : float
        Point size on screen, pixels.

    """
    from foxglove.messages import (
        Color,
        ImageAnnotations,
        Point2,
        PointsAnnotation,
        PointsAnnotationType,
    )

    rc = np.asarray(pixel_rc, dtype=np.float64).reshape(-1, 2)
    _require_finite('tag pixel_rc', rc)
    ts = foxglove_timestamp(stamp)
    points = [Point2(x=float(c) + 0.5, y=float(r) + 0.5) for r, c in rc]
    return ImageAnnotations(
        timestamp=ts,
        points=[
            PointsAnnotation(
                timestamp=ts,
                type=PointsAnnotationType.Points,
                points=points,
                outline_color=Color(r=color[0], g=color[1], b=color[2], a=color[3]),
                thickness=float(size_px),
            )
        ],
    )


def metrics_to_curves(metrics: Mapping) -> dict:
    """
    Convert one phase's metrics to the live view's curve point (a JSON object).

    The metrics are :func:`msg_to_metrics`'s; Foxglove's Plot panel reads the object
    (``/lv/curves.cavity_volume_ml`` against ``.time_fraction``).

    Keys: ``phase_index``, ``num_phases``, ``time_fraction`` (0..1), ``verdict`` (0 ok,
    1 degraded, 2 failed) and ``verdict_reasons``; then, except for a failed phase (no measurement:
    never plotted), ``cavity_volume_ml`` (ml), ``ejection_fraction`` (0..1), ``twist_apex_deg`` and
    ``twist_base_deg`` (degrees, the most apical / basal level, + counter-clockwise seen from the
    apex) and ``torsion_deg_per_cm``.
    """
    out = {
        'phase_index': int(metrics['phase_index']),
        'num_phases': int(metrics['num_phases']),
        'time_fraction': float(metrics['time_fraction']),
        'verdict': int(metrics['verdict']),
        'verdict_reasons': str(metrics['verdict_reasons']),
    }
    if out['verdict'] >= 2:
        return out
    twist = np.asarray(metrics['twist_deg'], dtype=np.float64)
    values = {
        'cavity_volume_ml': metrics['cavity_volume_ml'],
        'ejection_fraction': metrics['ejection_fraction'],
        'twist_apex_deg': twist[0] if twist.size else None,
        'twist_base_deg': twist[-1] if twist.size else None,
        'torsion_deg_per_cm': metrics['torsion_deg_per_cm'],
    }
    out.update({k: float(v) for k, v in values.items() if v is not None and np.isfinite(v)})
    return out


def curves_schema() -> dict:
    """
    Return the JSON schema of :func:`metrics_to_curves`'s objects.

    It is advertised with the channel, so Foxglove offers the fields before the first phase.
    """
    number = {'type': 'number'}
    props = {
        'phase_index': {'type': 'integer'},
        'num_phases': {'type': 'integer'},
        'time_fraction': number,
        'verdict': {'type': 'integer', 'description': '0 ok, 1 degraded, 2 failed (no values)'},
        'verdict_reasons': {'type': 'string'},
    }
    props.update({k: number for k in FOXGLOVE_CURVE_FIELDS})
    return {
        'type': 'object',
        'title': 'mlv_ros.PhaseCurves',
        'properties': props,
        'required': ['phase_index', 'num_phases', 'time_fraction', 'verdict'],
    }

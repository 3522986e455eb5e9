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
VTK XML files for ParaView, VisIt and any VTK reader.

Point clouds as ``.vtu`` and time series as ``.pvd``. Pure numpy + the standard library (no VTK, no
rclpy).

``.vtu`` (VTK XML UnstructuredGrid, file version 1.0): one ``VTK_VERTEX`` cell per point, so
the points show and filter as they are (no mesh is implied); data arrays inline ``binary`` —
base64 of a UInt64 byte count followed by the little-endian values, uncompressed — as VTK's own
writer emits them with ``SetDataModeToBinary`` and no compressor.

``.pvd`` (VTK XML ``Collection``): one ``<DataSet timestep=… file=…/>`` per file, the file
names relative to the ``.pvd``; ParaView opens it as one time series.

Public API
----------
write_vtu_points(path, points, point_data=None, field_data=None) -> Path
write_pvd(path, datasets) -> Path
"""

from __future__ import annotations

import base64
import os
from pathlib import Path
from typing import Iterable, Mapping
import xml.etree.ElementTree as ET

import numpy as np

VTK_VERTEX = 1
# numpy kinds/sizes ⇄ VTK XML type names (values are written little-endian).
_VTK_TYPES = {
    np.dtype(np.float32): 'Float32',
    np.dtype(np.float64): 'Float64',
    np.dtype(np.int8): 'Int8',
    np.dtype(np.int16): 'Int16',
    np.dtype(np.int32): 'Int32',
    np.dtype(np.int64): 'Int64',
    np.dtype(np.uint8): 'UInt8',
    np.dtype(np.uint16): 'UInt16',
    np.dtype(np.uint32): 'UInt32',
    np.dtype(np.uint64): 'UInt64',
}


def _vtk_type(values: np.ndarray) -> str:
    name = _VTK_TYPES.get(values.dtype.newbyteorder('='))
    if name is None:
        raise ValueError(f'no VTK data type for dtype {values.dtype}')
    return name


def _binary(values: np.ndarray) -> str:
    """Inline ``binary`` payload: base64(UInt64 byte count + little-endian values)."""
    data = np.ascontiguousarray(values, dtype=values.dtype.newbyteorder('<')).tobytes()
    return base64.b64encode(np.array([len(data)], dtype='<u8').tobytes() + data).decode('ascii')


def _data_array(
    parent: ET.Element, name: str | None, values: np.ndarray, components: int = 1
) -> ET.Element:
    attrs = {'type': _vtk_type(values)}
    if name is not None:
        attrs['Name'] = name
    if components > 1:
        attrs['NumberOfComponents'] = str(components)
    attrs['format'] = 'binary'
    el = ET.SubElement(parent, 'DataArray', attrs)
    el.text = _binary(values)
    return el


def _point_array(name: str, values, n: int) -> tuple[np.ndarray, int]:
    """``values`` as a flat array of ``n`` tuples and its component count (1 or the last axis)."""
    arr = np.asarray(values)
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    if arr.ndim == 1 and arr.shape[0] == n:
        return arr, 1
    if arr.ndim == 2 and arr.shape[0] == n and arr.shape[1] >= 1:
        return arr.reshape(-1), arr.shape[1]
    raise ValueError(f'point array {name!r} must have shape ({n},) or ({n}, k), got {arr.shape}')


def _write_xml(root: ET.Element, path: Path) -> Path:
    """Write ``root`` to ``path`` through a temporary file beside it (never a half file)."""
    ET.indent(root, space='  ')
    tmp = path.with_name(f'.{path.name}.tmp{os.getpid()}')
    try:
        with open(tmp, 'wb') as fh:
            fh.write(b'<?xml version="1.0"?>\n')
            fh.write(ET.tostring(root, encoding='utf-8'))
            fh.write(b'\n')
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_vtu_points(
    path,
    points,
    point_data: Mapping[str, np.ndarray] | None = None,
    field_data: Mapping[str, object] | None = None,
) -> Path:
    """
    Write a point cloud as a VTK XML UnstructuredGrid of vertices.

    Parameters
    ----------
    path : path-like
        The ``.vtu`` file (replaced if it exists).
    points : array_like, shape (N, 3)
        Positions; float32 is kept float32, anything else is written as float64.
    point_data : mapping of str to array_like, optional
        One array per name, shape (N,) (a scalar per point) or (N, k) (k components, e.g. a
        displacement vector). Any numeric dtype; bool is written as UInt8.
    field_data : mapping of str to scalar or 1-D array_like, optional
        Data of the whole dataset (e.g. ``time_fraction``, ``verdict``): numbers only (VTK
        string arrays are not read by every reader).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        A points array that is not (N, 3) or not finite, or a data array of the wrong length or
        a type VTK has no name for.

    """
    path = Path(path)
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f'points must have shape (N, 3), got {pts.shape}')
    if pts.dtype != np.float32:
        pts = pts.astype(np.float64)
    if not np.all(np.isfinite(pts)):
        raise ValueError('points must be finite')
    n = pts.shape[0]

    root = ET.Element(
        'VTKFile',
        {
            'type': 'UnstructuredGrid',
            'version': '1.0',
            'byte_order': 'LittleEndian',
            'header_type': 'UInt64',
        },
    )
    grid = ET.SubElement(root, 'UnstructuredGrid')
    if field_data:
        fd = ET.SubElement(grid, 'FieldData')
        for name, value in field_data.items():
            arr = np.atleast_1d(np.asarray(value))
            if arr.dtype == np.bool_:
                arr = arr.astype(np.uint8)
            if arr.ndim != 1 or arr.dtype.kind not in 'iuf':
                raise ValueError(
                    f'field data {name!r} must be a number or a 1-D numeric array, '
                    f'got {arr.dtype} {arr.shape}'
                )
            el = _data_array(fd, name, arr)
            el.set('NumberOfTuples', str(arr.size))
    piece = ET.SubElement(grid, 'Piece', {'NumberOfPoints': str(n), 'NumberOfCells': str(n)})
    arrays = {name: _point_array(name, values, n) for name, values in (point_data or {}).items()}
    pd_attrs = {}
    vectors = [name for name, (_, k) in arrays.items() if k == 3]
    scalars = [name for name, (_, k) in arrays.items() if k == 1]
    if vectors:
        pd_attrs['Vectors'] = vectors[0]
    if scalars:
        pd_attrs['Scalars'] = scalars[0]
    pd = ET.SubElement(piece, 'PointData', pd_attrs)
    for name, (flat, k) in arrays.items():
        _data_array(pd, name, flat, k)
    ET.SubElement(piece, 'CellData')
    _data_array(ET.SubElement(piece, 'Points'), 'Points', pts.reshape(-1), 3)
    cells = ET.SubElement(piece, 'Cells')
    _data_array(cells, 'connectivity', np.arange(n, dtype=np.int64))
    _data_array(cells, 'offsets', np.arange(1, n + 1, dtype=np.int64))
    _data_array(cells, 'types', np.full(n, VTK_VERTEX, dtype=np.uint8))
    return _write_xml(root, path)


def write_pvd(path, datasets: Iterable[tuple[float, str]]) -> Path:
    """
    Write a ParaView collection (time series) of ``(timestep, file)`` pairs, in the order given.

    ``file`` as it is to be found from the ``.pvd``'s directory (a relative name keeps the series
    movable). Timesteps must be finite and strictly increasing.
    """
    path = Path(path)
    root = ET.Element(
        'VTKFile', {'type': 'Collection', 'version': '0.1', 'byte_order': 'LittleEndian'}
    )
    coll = ET.SubElement(root, 'Collection')
    last = None
    for timestep, file in datasets:
        t = float(timestep)
        if not np.isfinite(t) or (last is not None and t <= last):
            raise ValueError(
                f'timesteps must be finite and strictly increasing, got {t!r} after {last!r}'
            )
        last = t
        ET.SubElement(
            coll, 'DataSet', {'timestep': repr(t), 'group': '', 'part': '0', 'file': str(file)}
        )
    return _write_xml(root, path)

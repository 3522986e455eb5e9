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
Image-plane geometry in DICOM patient coordinates (LPS, millimetres).

A pixel at row ``r``, column ``c`` lies at ``IPP + c·Δc·F_row + r·Δr·F_col`` where ``IPP`` is
ImagePositionPatient (centre of the first pixel), ``F_row``/``F_col`` are the two halves of
ImageOrientationPatient (``F_row`` points along increasing column index) and
``PixelSpacing = [Δr, Δc]`` (row spacing first). The slice normal is ``F_row × F_col``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_UNIT_TOL = 1e-4
_ORTHO_TOL = 1e-4


@dataclass(frozen=True)
class SliceGeometry:
    """
    Plane of one image in patient coordinates.

    Attributes
    ----------
    image_position : ndarray, shape (3,)
        Centre of pixel (row 0, column 0), mm (LPS).
    row_direction : ndarray, shape (3,)
        Unit vector along increasing column index.
    column_direction : ndarray, shape (3,)
        Unit vector along increasing row index.
    row_spacing, column_spacing : float
        Distance between adjacent rows / columns, mm.
    slice_thickness : float
        Slab thickness, mm.

    """

    image_position: np.ndarray
    row_direction: np.ndarray
    column_direction: np.ndarray
    row_spacing: float
    column_spacing: float
    slice_thickness: float

    def __post_init__(self):
        for name in ('image_position', 'row_direction', 'column_direction'):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if v.shape != (3,):
                raise ValueError(f'SliceGeometry.{name} must have 3 components, got {v.shape[0]}')
            if not np.all(np.isfinite(v)):
                raise ValueError(f'SliceGeometry.{name} is not finite: {v}')
            object.__setattr__(self, name, v)
        for name in ('row_direction', 'column_direction'):
            n = np.linalg.norm(getattr(self, name))
            if abs(n - 1.0) > _UNIT_TOL:
                raise ValueError(f'SliceGeometry.{name} must be a unit vector (norm {n:.6f})')
        if abs(float(self.row_direction @ self.column_direction)) > _ORTHO_TOL:
            raise ValueError('SliceGeometry row_direction and column_direction are not orthogonal')
        for name in ('row_spacing', 'column_spacing', 'slice_thickness'):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v <= 0:
                raise ValueError(
                    f'SliceGeometry.{name} must be a positive finite number of mm, got {v}'
                )
            object.__setattr__(self, name, v)

    @property
    def normal(self) -> np.ndarray:
        """Return the unit slice normal ``row_direction × column_direction``, shape (3,)."""
        n = np.cross(self.row_direction, self.column_direction)
        return n / np.linalg.norm(n)

    def pixel_to_patient(self, rc: np.ndarray) -> np.ndarray:
        """
        Map pixel coordinates to patient coordinates.

        Parameters
        ----------
        rc : array_like, shape (N, 2) or (2,)
            (row, column), pixels; may be fractional.

        Returns
        -------
        ndarray, shape (N, 3) or (3,)
            Patient coordinates, mm (LPS).

        """
        rc = np.asarray(rc, dtype=np.float64)
        flat = rc.reshape(-1, 2)
        xyz = (
            self.image_position
            + np.outer(flat[:, 1] * self.column_spacing, self.row_direction)
            + np.outer(flat[:, 0] * self.row_spacing, self.column_direction)
        )
        return xyz.reshape(rc.shape[:-1] + (3,))

    def patient_to_pixel(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Project patient coordinates onto the plane.

        Parameters
        ----------
        xyz : array_like, shape (N, 3) or (3,)
            Patient coordinates, mm.

        Returns
        -------
        rc : ndarray, shape (N, 2) or (2,)
            (row, column) of the orthogonal projection, pixels.
        offset : ndarray, shape (N,) or ()
            Signed distance from the plane along :attr:`normal`, mm.

        """
        xyz = np.asarray(xyz, dtype=np.float64)
        d = xyz.reshape(-1, 3) - self.image_position
        col = d @ self.row_direction / self.column_spacing
        row = d @ self.column_direction / self.row_spacing
        off = d @ self.normal
        rc = np.stack([row, col], axis=-1)
        return rc.reshape(xyz.shape[:-1] + (2,)), off.reshape(xyz.shape[:-1])

    def to_dicom(self) -> dict:
        """
        Return the DICOM attribute values of this geometry.

        ImagePositionPatient, ImageOrientationPatient, PixelSpacing, SliceThickness.
        """
        return {
            'ImagePositionPatient': [float(v) for v in self.image_position],
            'ImageOrientationPatient': [
                float(v) for v in np.concatenate([self.row_direction, self.column_direction])
            ],
            'PixelSpacing': [self.row_spacing, self.column_spacing],
            'SliceThickness': self.slice_thickness,
        }

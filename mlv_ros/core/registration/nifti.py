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
User myocardium masks from a NIfTI label volume, resampled onto the tagged ED planes.

:func:`masks_for_frames` turns a 3-D integer label image (e.g. an ACDC-style segmentation:
0 background, 1 RV, 2 myocardium, 3 LV cavity) into the per-slice boolean masks that
:func:`~mlv_ros.core.registration.register.register_ed` accepts as ``masks=``::

    masks, reasons = masks_for_frames("patient001_ED_gt.nii.gz", ed_frames, label=2)
    res = register_ed(ed_frames, masks=masks)    # slices without a mask: automatic segmentation

Placement. Every pixel centre of a frame is mapped to patient coordinates (DICOM LPS, mm) by its
:class:`~mlv_ros.core.geometry.SliceGeometry`, converted to the NIfTI world frame (RAS:
``x_RAS = −x_LPS``, ``y_RAS = −y_LPS``, ``z`` unchanged), and through the inverse of the image
affine (``img.affine``: nibabel's choice of sform/qform) to voxel indices; the label is sampled
there by nearest neighbour and ``mask = (label == label)``. Pixels outside the volume are False.
The volume and the images must share one patient frame (same scanner session / frame of
reference); nothing here registers one to the other.

Through-plane rule. The volume's *slice axis* is its voxel axis with the largest spacing ``s``
(for an isotropic volume any axis; it then never binds). For each myocardium pixel the distance
``δ`` along that axis from the pixel centre to the nearest voxel centre is measured
(``δ ≤ s / 2`` always). A pixel is "close" when ``δ ≤ tol`` with ``tol = max_distance_mm``, or by
default ``max(slice_thickness / 2, largest in-plane voxel spacing / 2)`` of the frame / volume,
i.e. the mask must come from a volume slice lying within the tagged slab. A frame is rejected
when more than 5 % of its myocardium pixels are not close. Consequences: an isotropic or fine
volume serves every plane (SA and LA); a stack of thick 2-D slices (e.g. a cine SA
segmentation, 10 mm apart) serves only the tagged planes parallel to it lying within ``tol`` of
one of its slices; a plane crossing the stack (LA through an SA stack) would get a staircase of
slices up to ``s / 2`` away and is rejected — those slices fall back to the automatic
segmentation in ``register_ed``.

Frames without a mask get a reason in ``reasons[(view, slice_index)]``: plane outside the volume,
too far from the stack's slices, or no pixel with the label on this plane.
"""

from __future__ import annotations

import os
from pathlib import Path

from mlv_ros.core.types import Frame
import numpy as np

#: Fraction of myocardium pixels allowed farther than the through-plane tolerance.
MAX_FAR_FRACTION = 0.05
_LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


def _load(path_or_img):
    """(label array int64 (I, J, K), affine (4, 4), name for messages)."""
    import nibabel as nib

    if isinstance(path_or_img, (str, os.PathLike)):
        name = str(path_or_img)
        p = Path(path_or_img)
        if not p.is_file():
            raise ValueError(f'NIfTI mask file {name}: no such file')
        try:
            img = nib.load(str(p))
        except Exception as e:  # nibabel raises ImageFileError, OSError, EOFError, ...
            raise ValueError(
                f'NIfTI mask file {name}: not a readable NIfTI image ({type(e).__name__}: {e})'
            ) from e
    else:
        img = path_or_img
        name = getattr(img, 'get_filename', lambda: None)() or f'<{type(img).__name__}>'
    if not isinstance(img, (nib.Nifti1Image, nib.Nifti2Image)):
        raise ValueError(f'NIfTI mask {name}: not a NIfTI image (got {type(img).__name__})')
    shape = tuple(int(n) for n in img.shape)
    try:
        data = np.asanyarray(img.dataobj)
    except Exception as e:
        raise ValueError(
            f'NIfTI mask {name}: cannot read the voxel data ({type(e).__name__}: {e})'
        ) from e
    while data.ndim > 3 and data.shape[-1] == 1:  # (I, J, K, 1) is a 3-D volume
        data = data[..., 0]
    if data.ndim == 2:  # a single 2-D slice: one voxel along k
        data = data[..., None]
    if data.ndim != 3:
        raise ValueError(
            f'NIfTI mask {name}: expected a 3-D label volume, got shape {shape}'
            + (' (4-D: pick one time point / ED first)' if len(shape) >= 4 else '')
        )
    if min(data.shape) < 1:
        raise ValueError(f'NIfTI mask {name}: empty volume, shape {shape}')
    if data.dtype == bool:
        data = data.astype(np.int64)
    elif np.issubdtype(data.dtype, np.floating):
        if not np.all(np.isfinite(data)):
            raise ValueError(f'NIfTI mask {name}: label volume has non-finite values')
        if not np.array_equal(data, np.round(data)):
            raise ValueError(
                f'NIfTI mask {name}: labels must be integers, got non-integer values '
                f'(dtype {data.dtype}; a probability map or image, not a label volume?)'
            )
        data = data.astype(np.int64)
    elif np.issubdtype(data.dtype, np.integer):
        data = data.astype(np.int64)
    else:
        raise ValueError(f'NIfTI mask {name}: labels must be integers, got dtype {data.dtype}')
    aff = np.asarray(img.affine, dtype=np.float64)
    if (
        aff.shape != (4, 4)
        or not np.all(np.isfinite(aff))
        or abs(np.linalg.det(aff[:3, :3])) < 1e-9
    ):
        raise ValueError(f'NIfTI mask {name}: affine is missing, non-finite or singular:\n{aff}')
    return data, aff, name


def masks_for_frames(path_or_img, frames, label: int = 2, max_distance_mm: float | None = None):
    """
    Per-slice myocardium masks for ``frames`` from a NIfTI label volume.

    Parameters
    ----------
    path_or_img : str, PathLike or nibabel Nifti1Image / Nifti2Image
        3-D integer label volume (a trailing singleton 4th dimension is accepted).
    frames : list of Frame
        Frames to mask (typically the ED frames); one mask per ``(view, slice_index)`` (the
        geometry of a slice is the same at every phase; the first frame of a slice is used).
    label : int
        Myocardium label (ACDC: 2).
    max_distance_mm : float, optional
        Through-plane tolerance (see the module docstring); default
        ``max(slice_thickness / 2, largest in-plane voxel spacing / 2)``.

    Returns
    -------
    masks : dict
        ``(view, slice_index) -> bool (rows, cols)`` for every frame that got a mask.
    reasons : dict
        ``(view, slice_index) -> str`` for every frame that did not.

    Raises
    ------
    ValueError
        Missing file, not NIfTI, not a 3-D volume, non-integer labels, singular affine, label
        not present anywhere in the volume, bad frames or tolerance. Messages name the file.

    """
    data, aff, name = _load(path_or_img)
    label = _checked_label(data, name, label)
    if max_distance_mm is not None and not (np.isfinite(max_distance_mm) and max_distance_mm > 0):
        raise ValueError(
            f'max_distance_mm must be a positive number of mm, got {max_distance_mm!r}'
        )
    if frames is None:
        raise ValueError('masks_for_frames needs a list of Frame records, got None')
    volume = _Volume(data, aff, name)
    masks: dict = {}
    reasons: dict = {}
    seen = set()
    for f in frames:
        if not isinstance(f, Frame):
            raise ValueError(f'frames must be Frame records, got {type(f).__name__}')
        key = (int(f.view), int(f.slice_index))
        if key in seen:
            continue
        seen.add(key)
        got = volume.plane_mask(f, label, max_distance_mm)
        if isinstance(got, str):
            reasons[key] = got
        else:
            masks[key] = got
    return masks, reasons


def _checked_label(data: np.ndarray, name: str, label) -> int:
    """Return ``label`` as an int, refusing a non-integer or one absent from the volume."""
    if isinstance(label, (bool, np.bool_)) or not float(label).is_integer():
        raise ValueError(f'NIfTI mask {name}: label must be an integer, got {label!r}')
    label = int(label)
    present = np.unique(data)
    if label not in present:
        shown = ', '.join(str(int(v)) for v in present[:20]) + (
            ', ...' if present.size > 20 else ''
        )
        raise ValueError(
            f'NIfTI mask {name}: myocardium label {label} does not occur in the volume '
            f'(labels present: {shown})'
        )
    return label


class _Volume:
    """A label volume with its affine, sampled on image planes (:func:`masks_for_frames`)."""

    def __init__(self, data: np.ndarray, aff: np.ndarray, name: str):
        """Keep the volume and derive its inverse affine, voxel spacing and slice axis."""
        self.data, self.aff, self.name = data, aff, name
        self.inv = np.linalg.inv(aff)
        self.spacing = np.linalg.norm(aff[:3, :3], axis=0)  # mm per voxel along i, j, k
        self.k_ax = int(np.argmax(self.spacing))
        self.inplane = float(np.max(np.delete(self.spacing, self.k_ax)))
        self.dims = np.array(data.shape)

    def plane_mask(self, f: Frame, label: int, max_distance_mm):
        """Return the myocardium mask of frame ``f``'s plane, bool (rows, cols), or why not."""
        data, name = self.data, self.name
        g = f.geometry
        rows, cols = np.asarray(f.image).shape[:2]
        rr, cc = np.meshgrid(
            np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64), indexing='ij'
        )
        xyz = g.pixel_to_patient(np.stack([rr.ravel(), cc.ravel()], 1)) * _LPS_TO_RAS
        ijk = xyz @ self.inv[:3, :3].T + self.inv[:3, 3]  # fractional voxel indices
        idx = np.rint(ijk).astype(np.int64)
        inside = np.all((idx >= 0) & (idx < self.dims), axis=1)
        if not inside.any():
            return f'plane lies outside the NIfTI volume {name} (shape {tuple(data.shape)})'
        lab = np.zeros(rows * cols, dtype=np.int64)
        ii = idx[inside]
        lab[inside] = data[ii[:, 0], ii[:, 1], ii[:, 2]]
        myo = lab == label
        if not myo.any():
            return (
                f'no voxel with label {label} on this plane in {name} '
                f'({int(inside.sum())} of {rows * cols} pixels inside the volume)'
            )
        tol = (
            float(max_distance_mm)
            if max_distance_mm is not None
            else max(0.5 * g.slice_thickness, 0.5 * self.inplane)
        )
        k_ax, spacing = self.k_ax, self.spacing
        delta = np.abs(ijk[myo, k_ax] - idx[myo, k_ax]) * spacing[k_ax]
        far = float(np.mean(delta > tol + 1e-6))
        if far > MAX_FAR_FRACTION:
            cosang = abs(float(g.normal @ (self.aff[:3, k_ax] * _LPS_TO_RAS)) / spacing[k_ax])
            how = (
                'is parallel to'
                if cosang > 0.985
                else f'crosses (at {np.degrees(np.arccos(min(cosang, 1.0))):.0f} deg)'
            )
            return (
                f'plane {how} the NIfTI slices ({spacing[k_ax]:.1f} mm apart) of {name}: '
                f'{100 * far:.0f} % of its myocardium pixels lie > {tol:.1f} mm (median '
                f'{float(np.median(delta)):.1f} mm) from a slice centre'
            )
        return myo.reshape(rows, cols)

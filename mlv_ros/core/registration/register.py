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
End-diastolic registration of the meshless LV model to tagged SA/LA images (paper §2.1, §3.2).

Pipeline of :func:`register_ed`:

1. long axis from the plane geometry (:func:`mlv_ros.core.io.dicom.estimate_long_axis`: LA
   planes' common line, else the SA normal; oriented apex → base);
2. per-slice myocardium: user masks (per-slice boolean arrays) where given, else the automatic
   tag-energy segmentation (:mod:`.segment`); a slice that fails gets a reason and is dropped;
3. 3-D myocardium reconstructed from all SA/LA contour points (:mod:`.initialise`), particles
   sampled inside it, polar model frame (c, R, a0..a3, τ, per-particle α, β, w);
4. registration (Fig. 7): on every slice, 50 landmarks (SA: 25 endo + 25 epi; LA: 25 per wall)
   are picked on the image contours by local curvature (:mod:`.landmarks`) and matched to the
   model's contour on the same slice along the same ray from the long axis; the pairs are
   in-plane external forces ``(I − n nᵀ)(t − x)`` for :meth:`MeshlessModel.fit`, which moves
   the global parameters first and then the local deformation. The registered particle cloud
   becomes the rest (ED) configuration for tracking. Without a usable LA view this step is
   skipped (in-plane SA forces leave the model's extent along the axis free; the fit drifted).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time

from mlv_ros.core.io.dicom import estimate_long_axis
from mlv_ros.core.meshless import MeshlessModel, ModelFrame
from mlv_ros.core.registration import segment as seg
from mlv_ros.core.registration.anatomy import (
    estimate_septum,
    SeptumEstimate,
    SOURCE_DETECTED,
    SOURCE_GIVEN,
)
from mlv_ros.core.registration.initialise import (
    AxisFrame,
    default_reference,
    LVShape,
    model_frame,
    reconstruct_shape,
    sample_particles,
)
from mlv_ros.core.registration.landmarks import curvature_landmarks, LANDMARKS_PER_SA_SLICE
from mlv_ros.core.types import Frame, ModelState, VIEW_LA, VIEW_SA
import numpy as np

#: Fewest usable SA slices for a 3-D reconstruction.
MIN_SA_SLICES = 3
_VIEW = {VIEW_SA: 'SA', VIEW_LA: 'LA'}


@dataclass
class SliceReport:
    """
    Outcome of the registration for one slice.

    ``ok`` and, if not, ``reason``; ``source`` is ``"auto"`` or ``"mask"``; ``landmarks`` used in
    the registration; ``residual_mm`` RMS in-plane landmark distance after registration (NaN if
    none); ``base_shown`` (LA) False when the view's horseshoe closed over the atrium, so that
    it could not say where the base is.
    """

    view: int
    slice_index: int
    ok: bool
    reason: str = ''
    source: str = 'auto'
    landmarks: int = 0
    residual_mm: float = float('nan')
    base_shown: bool = True


@dataclass
class RegistrationResult:
    """
    Registered ED model.

    Attributes
    ----------
    particles : ndarray, shape (N, 3)
        Registered particle cloud, patient coordinates (LPS), mm — the rest configuration for
        :class:`~mlv_ros.core.meshless.MeshlessModel`.
    frame : ModelFrame
        Polar model frame of ``particles`` (rest parameters c, R, a0..a3, τ = 0 and each
        particle's α, β, w); ``MeshlessModel(particles, frame)`` builds the tracking model.
    polar : dict
        ``alpha``, ``beta`` (rad), ``w`` (eq. 1 radial fraction, 1 on the fitted epicardial
        ellipsoid) and ``transmural`` (0 endo → 1 epi), each shape (N,).
    state : ModelState
        Rest global parameters plus the registration's iterations / residual / convergence.
    shape : LVShape
        The reconstructed myocardium (before registration).
    slice_reports : list of SliceReport
    warnings : list of str
    axis_point, axis_direction : ndarray, shape (3,)
        Long axis used (mm; unit vector apex → base).
    masks : dict
        ``(view, slice_index) -> bool (rows, cols)`` myocardium used for each usable slice.
    surfaces : dict
        ``"endo"``, ``"epi"``: registered wall-surface samples, (M, 3) mm.
    timings : dict
        Seconds per stage.
    septum : SeptumEstimate
        Where the septum (β = 0 is the inferior RV insertion 60° from it) came from: the RV found
        in the ED SA images (``source`` "detected"), the anatomical prior ("prior", with why), or
        the caller's ``reference_direction`` ("given").

    """

    particles: np.ndarray
    frame: ModelFrame
    polar: dict
    state: ModelState
    shape: LVShape
    slice_reports: list
    warnings: list
    axis_point: np.ndarray
    axis_direction: np.ndarray
    masks: dict = field(default_factory=dict)
    surfaces: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    septum: SeptumEstimate | None = None

    def wall_thickness_mm(self) -> np.ndarray:
        """
        Return the ED wall thickness of the registered model, mm, shape (M,).

        For each epicardial surface sample (:attr:`surfaces`), the distance to the nearest
        endocardial sample; empty without surfaces. At the apex this is the apical wall (epicardial
        to endocardial apex).
        """
        from scipy.spatial import cKDTree

        endo, epi = (
            np.asarray(self.surfaces.get(k, np.zeros((0, 3))), float).reshape(-1, 3)
            for k in ('endo', 'epi')
        )
        if not len(endo) or not len(epi):
            return np.zeros(0)
        return cKDTree(endo).query(epi)[0]


# --------------------------------------------------------------------------- helpers
def _fov_centre(f: Frame) -> np.ndarray:
    r, c = np.asarray(f.image).shape[:2]
    return f.geometry.pixel_to_patient(np.array([(r - 1) / 2.0, (c - 1) / 2.0]))


def _axis_in_plane(g, point, direction):
    """Intersection of the axis line with a (SA) plane, or None when nearly parallel."""
    n = g.normal
    den = float(direction @ n)
    if abs(den) < 0.2:
        return None
    t = float((g.image_position - point) @ n) / den
    return point + t * direction


def _ray_points(s: seg.SliceSegmentation, g, which: str) -> tuple[np.ndarray, np.ndarray]:
    """3-D points of the endo/epi radii of a segmentation; returns (points (K, 3), ray index)."""
    r = s.endo if which == 'endo' else s.epi
    ok = np.isfinite(r) & (r > 0.5)
    idx = np.flatnonzero(ok)
    rc = s.centre_rc[None] + r[idx, None] * np.stack(
        [np.sin(s.angles[idx]), np.cos(s.angles[idx])], 1
    )
    return g.pixel_to_patient(rc), idx


def _model_radii(
    shape: LVShape, g, centre_rc, angles, which: str, max_mm: float = 90.0
) -> np.ndarray:
    """
    Return the radius (px) along each in-plane ray where the wall ``which`` is first crossed.

    Crossed from inside the reconstructed wall (the model's contour on this slice); NaN where it is
    not crossed.
    """
    step_mm = 0.25
    t = np.arange(0.0, max_mm, step_mm)
    sp = g.row_spacing
    dirs = np.stack([np.sin(angles), np.cos(angles)], 1)
    rc = centre_rc[None, None] + (t / sp)[None, :, None] * dirs[:, None, :]
    x = g.pixel_to_patient(rc.reshape(-1, 2))
    r, th, z = shape.frame.to_cylindrical(x)
    surf = shape.endo if which == 'endo' else shape.epi
    gval = (r * r - surf.r2(z, th)).reshape(len(angles), -1)
    if which == 'epi':  # beyond the base or below the apex counts as outside
        zz = z.reshape(len(angles), -1)
        gval = np.where((zz > shape.z_base) | (zz < shape.z_apex_epi), np.abs(gval) + 1.0, gval)
    else:
        zz = z.reshape(len(angles), -1)
        gval = np.where(zz > shape.z_base, np.abs(gval) + 1.0, gval)
    out = np.full(len(angles), np.nan)
    neg = gval < 0
    cross = neg[:, :-1] & ~neg[:, 1:]
    has = cross.any(axis=1) & neg[:, 0]
    i = np.argmax(cross, axis=1)
    rows = np.flatnonzero(has)
    g0, g1 = gval[rows, i[rows]], gval[rows, i[rows] + 1]
    out[rows] = (t[i[rows]] + step_mm * g0 / (g0 - g1)) / sp
    return out


def _contour_landmarks(s: seg.SliceSegmentation, which: str, n: int) -> np.ndarray:
    """Ray indices of ``n`` curvature landmarks on one wall contour of a segmentation."""
    r = s.endo if which == 'endo' else s.epi
    idx = np.flatnonzero(np.isfinite(r) & (r > 0.5))
    if idx.size < max(n, 5):
        return np.zeros(0, np.int64)
    closed = idx.size == r.size
    if not closed:  # LA arc: order the rays along the horseshoe (it may wrap past ±π)
        gaps = np.flatnonzero(np.diff(idx) > 1)
        if gaps.size:
            idx = np.roll(idx, -(gaps[0] + 1))
    rc = s.centre_rc[None] + r[idx, None] * np.stack(
        [np.sin(s.angles[idx]), np.cos(s.angles[idx])], 1
    )
    return idx[curvature_landmarks(rc, min(n, idx.size), closed=closed)]


# --------------------------------------------------------------------------- main
def segment_around_axis(frames: list) -> dict:
    """
    Segment the ED myocardium of every frame automatically around the geometric long axis.

    As :func:`register_ed` segments (the batch counterpart of :class:`StreamingMasker`).

    Parameters
    ----------
    frames : list of Frame
        ED frames of one study (SA and LA).

    Returns
    -------
    dict
        ``{(view, slice_index): (mask or None, reason)}``; ``reason`` is empty on success.

    """
    sa = [f for f in frames if f.view == VIEW_SA]
    la = [f for f in frames if f.view != VIEW_SA]
    est = estimate_long_axis(
        [f.geometry for f in sa], [f.geometry for f in la], np.array([_fov_centre(f) for f in sa])
    )
    out = {}
    for f in frames:
        g, sp = f.geometry, f.geometry.row_spacing
        fam = seg.tag_families(f.tag_lines)
        if f.view == VIEW_SA:
            x = _axis_in_plane(g, est.point, est.direction)
            if x is None:
                out[(f.view, f.slice_index)] = (
                    None,
                    'SA plane is nearly parallel to the long axis',
                )
                continue
            s = seg.segment_sa(f.image, g.patient_to_pixel(x)[0], sp, families=fam)
        else:
            axis_rc = np.array(
                [est.direction @ g.column_direction, est.direction @ g.row_direction]
            )
            c = g.patient_to_pixel(est.point)[0]
            s = seg.segment_la(f.image, c, axis_rc, sp, families=fam)
        out[(f.view, f.slice_index)] = (s.mask if s.ok else None, s.reason)
    return out


def register_ed(
    frames: list,
    num_particles: int = 5000,
    masks=None,
    seed: int = 0,
    *,
    landmarks_per_sa_slice: int = LANDMARKS_PER_SA_SLICE,
    max_iterations: int = 20,
    local_iterations: int = 0,
    data_weight: float = 100.0,
    reference_direction=None,
) -> RegistrationResult:
    """
    Register the meshless LV model to the end-diastolic SA and LA tagged images.

    Parameters
    ----------
    frames : list of Frame
        ED frames (one per slice; if several phases of a slice are given the lowest
        ``phase_index`` is used), SA and LA together.
    num_particles : int
        Particles of the model (≥ 100; paper-scale default 5000).
    masks : optional
        User myocardium masks: a ``{(view, slice_index): bool (rows, cols)}`` dict, e.g. the
        first result of :func:`mlv_ros.core.registration.nifti.masks_for_frames` (NIfTI labels).
        Slices with a mask skip the automatic segmentation; a mask whose shape differs from its
        image is rejected (reason).
    seed : int
        Particle-sampling seed (deterministic output).
    landmarks_per_sa_slice : int
        Paper: 50 (split evenly endo/epi; LA planes get the same number).
    max_iterations : int
        Cap on global-stage iterations of the meshless fit.
    local_iterations : int
        Cap on global+local iterations after the global stage. Default 0 (global deformation
        only): on the simulator a time-boxed local stage (truncated CG) moved interior particles
        off and lowered the inside fraction from 98 % to 93 %.
    data_weight : float
        External-force weight of :meth:`MeshlessModel.fit`.
    reference_direction : array_like, shape (3,), optional
        β = 0 direction (patient). Default: the inferior RV insertion 60° from the septum found in
        the ED SA images (:mod:`~.anatomy`), else :func:`~.initialise.default_reference` (the
        anatomical prior, with a warning).

    Returns
    -------
    RegistrationResult

    Raises
    ------
    ValueError
        No frames, no SA view, fewer than :data:`MIN_SA_SLICES` usable SA slices (the message
        lists each slice's reason), or a reconstruction that fails.

    """
    t0 = time.perf_counter()
    if landmarks_per_sa_slice < 2:
        raise ValueError(
            f'landmarks_per_sa_slice must be >= 2 (endo + epi), got {landmarks_per_sa_slice}'
        )
    timings: dict = {}
    warnings: list[str] = []
    by_key = _ed_frames(frames, warnings)
    sa_keys = sorted(k for k in by_key if k[0] == VIEW_SA)
    la_keys = sorted(k for k in by_key if k[0] == VIEW_LA)
    est = estimate_long_axis(
        [by_key[k].geometry for k in sa_keys],
        [by_key[k].geometry for k in la_keys],
        np.array([_fov_centre(by_key[k]) for k in sa_keys]),
    )
    axis_pt, axis_dir = est.point, est.direction

    ts = time.perf_counter()
    segs, reports = _segment_slices(by_key, sa_keys + la_keys, axis_pt, axis_dir, masks or {})
    timings['segmentation'] = time.perf_counter() - ts
    usable_sa = _usable_sa_slices(sa_keys, la_keys, segs, reports, warnings)
    usable_la = [k for k in la_keys if k in segs]

    ref, septum = _reference(by_key, segs, usable_sa, axis_dir, reference_direction)
    frame3 = AxisFrame(axis_pt, axis_dir, _perp(ref, axis_dir))
    if la_keys and not usable_la:
        warnings.append('no usable LA view: apex and base are extrapolated from the SA stack')

    # ---- 3-D reconstruction (§2.1)
    ts = time.perf_counter()
    shape = _reconstruct(by_key, segs, usable_sa, frame3, warnings, reports)
    particles0 = sample_particles(shape, int(num_particles), seed)
    mframe, polar = model_frame(shape, particles0)
    timings['initialisation'] = time.perf_counter() - ts

    # ---- landmark registration (§3.2, Fig. 7)
    ts = time.perf_counter()
    landmarks = _landmark_pairs(by_key, segs, shape, landmarks_per_sa_slice)
    settings = (max_iterations, local_iterations, data_weight)
    particles, state_kw, surf_model = _fit_landmarks(
        particles0, mframe, landmarks, reports, warnings, bool(usable_la), settings
    )
    timings['registration'] = time.perf_counter() - ts

    if particles is not particles0:
        mframe, polar = model_frame(shape, particles)
    polar['transmural'] = shape.transmural(particles0)
    state = _ed_state(mframe, next(iter(by_key.values())).num_phases, len(particles), state_kw)
    timings['total'] = time.perf_counter() - t0
    return RegistrationResult(
        particles,
        mframe,
        polar,
        state,
        shape,
        reports,
        warnings,
        axis_pt,
        axis_dir,
        {k: s.mask for k, s in segs.items()},
        _surfaces(shape, surf_model, particles),
        timings,
        septum,
    )


def _ed_state(mframe: ModelFrame, num_phases, num_particles: int, fit: dict) -> ModelState:
    """Return the registered model's ED state: its global parameters and the fit's figures."""
    return mframe.params.state(num_particles, phase_index=0, num_phases=int(num_phases), **fit)


def _ed_frames(frames, warnings: list) -> dict:
    """
    Return each slice's ED frame, ``{(view, slice_index): Frame}``; say what is missing.

    A slice given several phases keeps its lowest; a study without SA slices is refused.
    """
    if frames is None or len(frames) == 0:
        raise ValueError('register_ed needs the ED frames of the SA (and LA) slices; got none')
    by_key: dict = {}
    for f in frames:
        if not isinstance(f, Frame):
            raise ValueError(f'frames must be Frame records, got {type(f).__name__}')
        k = (int(f.view), int(f.slice_index))
        if k not in by_key or f.phase_index < by_key[k].phase_index:
            by_key[k] = f
    if any(f.phase_index != 0 for f in by_key.values()):
        warnings.append('some slices have no phase-0 (ED) frame; their earliest phase was used')
    views = [k[0] for k in by_key]
    if VIEW_SA not in views:
        raise ValueError('no SA frames: the registration needs a short-axis stack')
    la = views.count(VIEW_LA)
    if not la:
        warnings.append('no LA views: apex and base are extrapolated from the SA stack')
    elif la < 2:
        warnings.append('only one LA view: the long axis comes from the SA normal')
    return by_key


def _segment_slices(by_key: dict, keys: list, axis_pt, axis_dir, user: dict):
    """
    Segment each slice around the long axis (or take the user's mask).

    Returns ``(segs, reports)``: ``{key: SliceSegmentation}`` of the slices segmented, and one
    :class:`SliceReport` per slice, in ``keys`` order (a dropped slice with its reason).
    """
    segs: dict = {}
    reports: list[SliceReport] = []
    for k in keys:
        s = _segment_slice(by_key[k], k, axis_pt, axis_dir, user)
        if isinstance(s, str):
            reports.append(SliceReport(*k, False, s))
        elif not s.ok:
            reports.append(SliceReport(*k, False, s.reason, s.source))
        else:
            segs[k] = s
            reports.append(SliceReport(*k, True, '', s.source))
    return segs, reports


def _segment_slice(f: Frame, k: tuple, axis_pt, axis_dir, user: dict):
    """
    Return one slice's segmentation (``source`` 'mask' or 'auto'), or why it cannot be had.

    The user's mask of the slice (``user[k]``) is taken where given.

    The reason (a str) is for a slice whose geometry does not fit the long axis or whose pixels
    are anisotropic.
    """
    g = f.geometry
    img = np.asarray(f.image)
    sp = g.row_spacing
    if abs(g.row_spacing - g.column_spacing) > 1e-3 * sp:
        return 'anisotropic pixel spacing is not supported'
    axis_rc = None
    if k[0] == VIEW_SA:
        x = _axis_in_plane(g, axis_pt, axis_dir)
        if x is None:
            return 'SA plane is nearly parallel to the long axis'
        centre_rc = g.patient_to_pixel(x)[0]
    else:
        centre_rc, off = g.patient_to_pixel(axis_pt)
        axis_rc = np.array([axis_dir @ g.column_direction, axis_dir @ g.row_direction])
        if abs(off) > 10.0 or np.linalg.norm(axis_rc) < 0.9:
            return (
                f'LA plane does not contain the long axis '
                f'({abs(off):.1f} mm off, in-plane cos {np.linalg.norm(axis_rc):.2f})'
            )
    if k in user:
        s = _from_mask(user[k], img.shape, k[0], centre_rc, sp, axis_rc)
        s.source = 'mask'
        return s
    if k[0] == VIEW_SA:
        s = seg.segment_sa(img, centre_rc, sp, families=seg.tag_families(f.tag_lines))
    else:
        s = seg.segment_la(img, centre_rc, axis_rc, sp, families=seg.tag_families(f.tag_lines))
    s.source = 'auto'
    return s


def _usable_sa_slices(sa_keys, la_keys, segs: dict, reports: list, warnings: list) -> list:
    """Return the segmented SA slices; refuse fewer than MIN_SA_SLICES, naming each reason."""
    usable_sa = [k for k in sa_keys if k in segs]
    if len(usable_sa) < MIN_SA_SLICES:
        why = '; '.join(
            f'{_VIEW[r.view]} {r.slice_index}: {r.reason}' for r in reports if not r.ok
        )
        raise ValueError(
            f'only {len(usable_sa)} usable SA slices (need >= {MIN_SA_SLICES}): '
            f'{why or "none given"}'
        )
    failed = [r for r in reports if not r.ok]
    if failed:
        warnings.append(
            f'registered from {len(segs)} of {len(sa_keys) + len(la_keys)} slices; dropped: '
            + ', '.join(f'{_VIEW[r.view]} {r.slice_index}' for r in failed)
        )
    return usable_sa


def _reference(by_key, segs, usable_sa, axis_dir, reference_direction):
    """
    Return the circumferential reference (β = 0) and where its septum came from.

    The caller's direction, else the septum from the RV in the images, else the prior.
    """
    if reference_direction is not None:
        ref = np.asarray(reference_direction, float)
        septum = SeptumEstimate(
            SOURCE_GIVEN,
            default_reference(axis_dir, septum_hint=ref, rotate_deg=-60.0),
            reason='reference_direction given by the caller',
        )
        return ref, septum
    septum = estimate_septum(
        [(np.asarray(by_key[k].image), segs[k], by_key[k].geometry) for k in usable_sa],
        axis_dir,
        default_reference(axis_dir, rotate_deg=0.0),
    )
    if septum.source == SOURCE_DETECTED:
        return default_reference(axis_dir, septum_hint=septum.septum), septum
    # The segments are then not tied to the anatomy (septum.reason says why).
    return default_reference(axis_dir), septum


def _reconstruct(
    by_key, segs, usable_sa, frame3: AxisFrame, warnings: list, reports=()
) -> LVShape:
    """
    Reconstruct the 3-D myocardium from every slice's contour points (§2.1).

    An LA view whose horseshoe closed over the atrium has no base cut of its own
    (``base_level`` NaN): it is cut where the other views put the base, and its report's
    ``base_shown`` is set False.
    """
    axis_pt, axis_dir = frame3.origin, frame3.axis  # the long axis the slices were cut along
    endo_pts, epi_pts, we, wn = [], [], [], []
    z_bases, z_cut, closed = [], [], []
    for k, s in segs.items():
        g = by_key[k].geometry
        pe, _ = _ray_points(s, g, 'epi')
        pn, _ = _ray_points(s, g, 'endo')
        zb = np.inf
        if k[0] == VIEW_LA:
            if np.isfinite(s.base_level):
                base_pt = g.pixel_to_patient(s.centre_rc + s.base_level * s.axis_rc)
                zb = float((base_pt - axis_pt) @ axis_dir)
                z_bases.append(zb)
            else:
                closed.append(k)
            w = 2.0  # LA rays are sparser per unit surface than the SA stack's
        else:
            w = 1.0
        epi_pts.append(pe)
        endo_pts.append(pn)
        z_cut.append(zb)
        we.append(np.full(len(pe), w))
        wn.append(np.full(len(pn), w))
    if closed:
        warnings.append(
            f'{_names(closed)}: the horseshoe closes over the atrium (the edges of its blood '
            'read as wall), so '
            + (
                'the base is taken from the other LA views'
                if z_bases
                else 'no LA view shows the base: the model ends half a slice above the most '
                'basal SA slice and leaves out the wall above it'
            )
        )
    z_base = _base_level(by_key, usable_sa, axis_pt, axis_dir, z_bases, warnings)
    for i, k in enumerate(segs):
        if k[0] != VIEW_LA:
            continue
        # Ray ends at the base cut are not wall points; a view closed over the atrium is cut
        # where the base is taken.
        keep = (z_cut[i] if np.isfinite(z_cut[i]) else z_base) - 3.0
        e_in = (epi_pts[i] - axis_pt) @ axis_dir < keep
        n_in = (endo_pts[i] - axis_pt) @ axis_dir < keep
        epi_pts[i], we[i] = epi_pts[i][e_in], we[i][e_in]
        endo_pts[i], wn[i] = endo_pts[i][n_in], wn[i][n_in]
    for k in closed:
        _cut_at_base(segs[k], by_key[k].geometry, axis_pt, axis_dir, z_base)
    for r in reports:
        if (r.view, r.slice_index) in closed:
            r.base_shown = False
    return reconstruct_shape(frame3, endo_pts, epi_pts, z_base, wn, we)


def _names(keys) -> str:
    """Return slices' names for a message, e.g. ``LA 0, LA 2``."""
    return ', '.join(f'{_VIEW[k[0]]} {k[1]}' for k in keys)


def _cut_at_base(s: seg.SliceSegmentation, g, axis_pt, axis_dir, z_base: float) -> None:
    """Set an LA view's base level to ``z_base`` (mm on the long axis) and cut its mask there."""
    z_centre, z_step = (
        (g.pixel_to_patient(np.stack([s.centre_rc, s.centre_rc + s.axis_rc])) - axis_pt) @ axis_dir
    )
    s.base_level = float((z_base - z_centre) / (z_step - z_centre))
    s.mask &= seg.below_base(s.mask.shape, s.centre_rc, s.axis_rc, s.base_level)


def _base_level(by_key, usable_sa, axis_pt, axis_dir, z_bases: list, warnings: list) -> float:
    """
    Return the base's height on the long axis, mm: the LA views' base cut (median).

    The myocardium reaches at least the most basal segmented SA slice (where the long axis
    crosses it); without an LA view, half a slice thickness beyond it. A view whose horseshoe
    ends below that slice is contradicted by the SA stack's tagged annulus there (its wall was
    lost or cut short), so the median is over the views that reach it, when any does.
    """
    z_sa_top = max(
        float((_axis_in_plane(by_key[k].geometry, axis_pt, axis_dir) - axis_pt) @ axis_dir)
        for k in usable_sa
    )
    if not z_bases:
        return z_sa_top + 0.5 * by_key[usable_sa[0]].geometry.slice_thickness
    reaching = [z for z in z_bases if z >= z_sa_top]
    z_base = float(np.median(reaching or z_bases))
    if z_base < z_sa_top:
        # A horseshoe cut short (thick slab, faint base) would otherwise drop every SA slice
        # above it.
        warnings.append(
            f'LA views end {z_sa_top - z_base:.0f} mm below the most basal segmented SA '
            'slice; '
            'the base is taken at that slice'
        )
        z_base = z_sa_top
    return z_base


def _landmark_pairs(by_key, segs, shape: LVShape, landmarks_per_sa_slice: int) -> tuple:
    """
    Return the landmark pairs of every slice (Fig. 7) as lists per slice and wall.

    ``(sources, targets, normals, owner)``: model contour points, the image contour points on
    the same rays, the planes' normals, and the slice key of each pair. LA pairs within 3 mm of
    the base cut are left out.
    """
    axis_pt, axis_dir = shape.frame.origin, shape.frame.axis
    ctrl_rest, targets, normals, owner = [], [], [], []
    n_each = landmarks_per_sa_slice // 2
    for k, s in segs.items():
        g = by_key[k].geometry
        for which in ('endo', 'epi'):
            lm = _contour_landmarks(s, which, n_each)
            if lm.size == 0:
                continue
            model_r = _model_radii(shape, g, s.centre_rc, s.angles[lm], which)
            img_r = (s.endo if which == 'endo' else s.epi)[lm]
            ok = np.isfinite(model_r) & np.isfinite(img_r)
            d = np.stack([np.sin(s.angles[lm]), np.cos(s.angles[lm])], 1)
            src = g.pixel_to_patient(s.centre_rc[None] + model_r[:, None] * d)
            dst = g.pixel_to_patient(s.centre_rc[None] + img_r[:, None] * d)
            if k[0] == VIEW_LA:  # keep clear of the base cut
                zb = shape.z_base - 3.0
                ok &= ((src - axis_pt) @ axis_dir < zb) & ((dst - axis_pt) @ axis_dir < zb)
            ctrl_rest.append(src[ok])
            targets.append(dst[ok])
            normals.append(np.tile(g.normal, (int(ok.sum()), 1)))
            owner += [k] * int(ok.sum())
    return ctrl_rest, targets, normals, owner


def _fit_landmarks(
    particles0,
    mframe,
    landmarks: tuple,
    reports: list,
    warnings: list,
    has_la: bool,
    settings: tuple,
):
    """
    Fit the model to the landmark pairs; keep the fit only where it brings the contours closer.

    ``settings`` are :func:`register_ed`'s ``(max_iterations, local_iterations, data_weight)``.

    Returns ``(particles, state_kw, model)``: the registered particles (``particles0`` when the
    fit is skipped or kept out, with the reason in ``warnings``), the ED state's fit fields, and
    the fitted model (None without a fit). Each slice's report gets its landmark count and
    residual.
    """
    unfitted = {'iterations': 0, 'residual': 0.0, 'converged': False, 'num_control_points': 0}
    kept = (particles0, unfitted, None)
    ctrl_rest = landmarks[0]
    if not has_la:
        # In-plane SA forces do not see the model's extent along the axis, and the global
        # stage's scale couples it to the radii: without an LA view the fit drifts along the
        # axis (measured, normal LV, SA only: 99.8 % of particles inside the true myocardium
        # as reconstructed, 50–79 % after the fit, depending on sub-millimetre contour details).
        warnings.append(
            'no usable LA view: landmark registration skipped (the axial scale is '
            'unobservable from SA slices); kept the reconstructed model'
        )
        return kept
    if not ctrl_rest or sum(len(c) for c in ctrl_rest) < 12:
        warnings.append('too few landmarks for registration; kept the reconstructed model')
        return kept
    src, dst, nrm = (np.concatenate(x) for x in landmarks[:3])
    max_iterations, local_iterations, data_weight = settings
    try:
        model = MeshlessModel(particles0, mframe)
        ctrl = model.attach(src)
        # Global stage first (rigid + scale + twist, eq. 9-15), then a bounded local stage:
        # the reconstruction already sits within ~1 mm, so a few local steps suffice.
        model.fit(
            ctrl, dst, plane_normals=nrm, max_iterations=max_iterations, local=False, tol=1e-3
        )
        fit = model.fit(
            ctrl,
            dst,
            plane_normals=nrm,
            max_iterations=local_iterations,
            data_weight=data_weight,
            cg_maxiter=25,
            refresh_every=0,
            tol=1e-2,
            local_start=np.inf,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        warnings.append(f'landmark registration failed ({exc}); kept the reconstructed model')
        return kept
    moved = ctrl.weights @ fit.positions
    proj = np.eye(3)[None] - nrm[:, :, None] * nrm[:, None, :]
    res = np.linalg.norm(np.einsum('mab,mb->ma', proj, dst - moved), axis=1)
    res0 = np.linalg.norm(np.einsum('mab,mb->ma', proj, dst - src), axis=1)
    closer = np.sqrt(np.mean(res**2)) <= np.sqrt(np.mean(res0**2))
    if not (np.all(np.isfinite(fit.positions)) and closer):
        warnings.append(
            'landmark registration did not reduce the contour distance; '
            'kept the reconstructed model'
        )
        return kept
    _report_landmarks(reports, np.array(landmarks[3]), res)
    state_kw = {
        'iterations': fit.iterations,
        'residual': float(np.sqrt(np.mean(res**2))),
        'converged': bool(fit.converged),
        'num_control_points': len(src),
    }
    return fit.positions, state_kw, model


def _report_landmarks(reports: list, owner: np.ndarray, res: np.ndarray) -> None:
    """Give each slice's report its landmark count and in-plane residual (RMS, mm)."""
    for r in reports:
        sel = (
            np.all(owner == (r.view, r.slice_index), axis=1) if len(owner) else np.zeros(0, bool)
        )
        r.landmarks = int(sel.sum())
        if sel.any():
            r.residual_mm = float(np.sqrt(np.mean(res[sel] ** 2)))


def _surfaces(shape: LVShape, model, particles) -> dict:
    """Return the endo- and epicardial surface samples, moved with the fit where there was one."""
    surfaces = {}
    for which in ('endo', 'epi'):
        points = shape.surface_points(which)
        if model is not None:
            try:
                points = model.attach(points).weights @ particles
            except ValueError:
                pass
        surfaces[which] = points
    return surfaces


def _perp(v, axis) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    v = v - (v @ axis) * axis
    n = np.linalg.norm(v)
    if n < 1e-6:
        raise ValueError('reference_direction is parallel to the long axis')
    return v / n


def _from_mask(mask, shape, view, centre_rc, spacing, axis_rc) -> seg.SliceSegmentation:
    """Polar contours of a user mask (same ray machinery as the automatic segmentation)."""
    m = np.asarray(mask)
    name = _VIEW[view]
    if m.shape != tuple(shape):
        return seg.SliceSegmentation(
            False,
            f'user mask shape {m.shape} does not match the image {tuple(shape)}',
            np.zeros(shape, bool),
            view=name,
        )
    m = m.astype(bool)
    if m.sum() < 20:
        return seg.SliceSegmentation(
            False,
            f'user mask has only {int(m.sum())} myocardium pixels',
            np.zeros(shape, bool),
            view=name,
        )
    return seg.segment_from_mask(m, centre_rc, spacing, axis_rc)

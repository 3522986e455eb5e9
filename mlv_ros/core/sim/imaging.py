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
Tagged-MRI image formation: slice planning, SPAMM tags carried by the material, slab profile.

Signal model (per sample point ``x`` of an image at trigger time ``t``)
---------------------------------------------------------------------
``X = motion.inverse(x, t)`` is the ED material position of whatever sits at ``x``:

* myocardium (``X`` inside the ED wall): ``M_myo · (E P(X) + 1 − E)``;
* blood (``X`` in the cavity or atrium, or the RV's): ``M_blood`` — flow washes the tags out;
* the RV free wall (:mod:`mlv_ros.core.sim.rv`, when the preset has ``geometry.rv``) is tagged
  like myocardium;
* background tissue (static, inside a sphere around the LV): ``M_bg · (E P(x) + 1 − E)``, or
  ``M_bg`` untagged with ``imaging.background_tagged: false``; air 0.

``P(X) = sin²(π a / λ) · sin²(π b / λ)`` is the 1-1 SPAMM grid at 45° flips (method notes,
"Tags"): ``a, b`` are the in-plane coordinates of ``X`` along the image's row and column
directions (turned by ``imaging.tag_angle_deg``, default 0) measured from the image centre, λ
the tag spacing, so dark tag planes ⟂ the image lie at ``a, b ∈ λℤ``. With
``imaging.tag_lines: single`` (one family of parallel tag lines, a real protocol) ``P(X) =
sin²(π a / λ)``; the default ``grid`` draws both families. ``E = exp(−t / T1)``
fades the tags. The slab is integrated over sub-planes at offsets ``±0.75·thickness`` along the
normal with Gaussian weights (FWHM = thickness); each sub-plane point is mapped back on its
own, so through-plane motion is real. A Gaussian in-plane PSF (``psf_sigma_px``) stands in for
the finite k-space window, then Rician noise ``|S + σ(n₁ + i n₂)|`` with ``σ = M_myo / SNR`` is
added.
"""

from __future__ import annotations

from dataclasses import dataclass

from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
from scipy.ndimage import gaussian_filter


@dataclass(frozen=True)
class PlannedSlice:
    """
    One image plane of the acquisition.

    Attributes
    ----------
    view : int
        ``VIEW_SA`` or ``VIEW_LA``.
    index : int
        Index within its view (SA 0 = most basal, or most apical with ``sa_order: apex_first``;
        LA k = the k-th angle of :func:`la_plane_angles`).
    geometry : SliceGeometry
        Plane, pixel grid and slab thickness.
    description : str
        DICOM SeriesDescription, e.g. ``"tagged SA 3"`` or ``"tagged LA 60deg"``.
    level : float
        SA: ED fractional level of the plane (0 apex, 1 base); LA: angle from the septum, deg.

    """

    view: int
    index: int
    geometry: SliceGeometry
    description: str
    level: float


def _geometry(centre, row_dir, col_dir, size, spacing, thickness) -> SliceGeometry:
    """Plane whose pixel grid is centred on ``centre`` (mm)."""
    half = 0.5 * (size - 1) * spacing
    ipp = np.asarray(centre) - half * np.asarray(row_dir) - half * np.asarray(col_dir)
    return SliceGeometry(ipp, row_dir, col_dir, spacing, spacing, thickness)


SA_ORDERS = ('base_first', 'apex_first')
SA_NORMALS = ('base_to_apex', 'apex_to_base')


def _rotate_in_plane(row, col, angle_deg: float):
    """Row/column directions turned by ``angle_deg`` about their normal (row toward column)."""
    if not angle_deg:
        return row, col
    a = np.radians(float(angle_deg))
    return np.cos(a) * row + np.sin(a) * col, -np.sin(a) * row + np.cos(a) * col


def _shift(imaging: dict, key: str) -> tuple[float, float]:
    v = imaging.get(key) or (0.0, 0.0)
    if len(v) != 2:
        raise ValueError(f'imaging.{key} must be two numbers (mm along rows, columns), got {v!r}')
    return float(v[0]), float(v[1])


def la_plane_angles(imaging: dict) -> tuple[list[float], list[bool]]:
    """
    Angles (deg) and normal flips of the LA planes of an ``imaging`` section.

    ``imaging.la_angles_deg`` (a list, one angle per plane, from the septum, counter-clockwise
    seen from the apex) wins over ``la_planes`` × ``la_angle_step_deg`` (planes at
    ``0, step, 2·step, …``); ``imaging.la_flip`` (one bool per plane, default all False)
    reverses a plane's normal by mirroring its row direction.

    Raises
    ------
    ValueError
        ``la_flip`` has a different length than the angles.

    """
    angles = imaging.get('la_angles_deg')
    if angles is None:
        step = float(imaging['la_angle_step_deg'])
        angles = [k * step for k in range(int(imaging['la_planes']))]
    else:
        angles = [float(a) for a in angles]
    flips = imaging.get('la_flip')
    flips = [False] * len(angles) if flips is None else [bool(f) for f in flips]
    if len(flips) != len(angles):
        raise ValueError(f'imaging.la_flip has {len(flips)} entries for {len(angles)} LA planes')
    return angles, flips


def plan_slices(
    motion: LVMotion, imaging: dict, size: int | None = None, pixel_spacing: float | None = None
) -> list[PlannedSlice]:
    """
    SA stack plus LA planes through the long axis (paper Fig. 6).

    Parameters
    ----------
    motion : LVMotion
        Supplies the long-axis frame and length.
    imaging : dict
        The preset's ``imaging`` section. Besides the required keys it reads these optional
        ones (defaults = the original fixed protocol):

        ``sa_order`` : ``"base_first"`` (default) or ``"apex_first"``
            Which end of the stack gets SA index 0.
        ``sa_normal`` : ``"base_to_apex"`` (default) or ``"apex_to_base"``
            Sign of the SA normal ``row × column``; ``apex_to_base`` negates the column
            direction (the image is mirrored top–bottom).
        ``sa_inplane_deg`` : float, default 0
            SA row direction turned this far (deg, toward the column direction) from the
            septum.
        ``la_angles_deg``, ``la_flip`` : list, optional
            See :func:`la_plane_angles`.
        ``la_inplane_deg`` : float, default 0
            LA row/column directions turned this far (deg) about the plane normal; 0 puts the
            base at the top of the image.
        ``sa_fov_shift_mm``, ``la_fov_shift_mm`` : [float, float], default [0, 0]
            Image centre moved off the long axis along the image's row and column directions,
            mm (the heart then sits off-centre by the opposite amount).
    size : int, optional
        Rows = columns (default ``imaging.size``).
    pixel_spacing : float, optional
        mm (default ``imaging.pixel_spacing_mm``).

    Returns
    -------
    list of PlannedSlice
        SA slices first (index 0 the most basal, or the most apical with ``apex_first``),
        then LA planes in ``la_angles_deg`` order.

    Raises
    ------
    ValueError
        The stack does not fit between base and apex, or an optional key has a bad value.

    """
    f = motion.frame
    L = motion.length
    n = int(size or imaging['size'])
    dx = float(pixel_spacing or imaging['pixel_spacing_mm'])
    th = float(imaging['slice_thickness_mm'])
    z_top = L - float(imaging['sa_base_gap_mm'])
    z_bot = float(imaging['sa_apex_gap_mm'])
    n_sa = int(imaging['sa_slices'])
    if not z_bot < z_top:
        raise ValueError('imaging.sa_base_gap_mm + sa_apex_gap_mm must be less than the LV length')
    order = imaging.get('sa_order', 'base_first')
    sa_normal = imaging.get('sa_normal', 'base_to_apex')
    if order not in SA_ORDERS:
        raise ValueError(f'imaging.sa_order must be one of {SA_ORDERS}, got {order!r}')
    if sa_normal not in SA_NORMALS:
        raise ValueError(f'imaging.sa_normal must be one of {SA_NORMALS}, got {sa_normal!r}')
    out = []
    # SA: rows run along e_2, columns along the septal direction; the normal is base → apex
    # (by default: sa_inplane_deg turns both, apex_to_base mirrors the column direction).
    row = f.septum
    col = np.cross(-f.long_axis, row)
    row, col = _rotate_in_plane(row, col, imaging.get('sa_inplane_deg', 0.0))
    if sa_normal == 'apex_to_base':
        col = -col
    s_row, s_col = _shift(imaging, 'sa_fov_shift_mm')
    heights = np.linspace(z_top, z_bot, n_sa)
    if order == 'apex_first':
        heights = heights[::-1]  # the same planes, numbered from the apex
    for k, z in enumerate(heights):
        centre = f.apex + z * f.long_axis
        if s_row or s_col:
            centre = centre + s_row * row + s_col * col
        g = _geometry(centre, row, col, n, dx, th)
        out.append(PlannedSlice(VIEW_SA, k, g, f'tagged SA {k}', float(z / L)))
    # LA: columns along the radial direction at angle β, rows from base (top) to apex (bottom).
    angles, flips = la_plane_angles(imaging)
    extra = motion.atrium_height
    centre_z = 0.5 * (L + min(extra, 20.0))
    l_row, l_col = _shift(imaging, 'la_fov_shift_mm')
    la_rot = imaging.get('la_inplane_deg', 0.0)
    for k, (beta_deg, flip) in enumerate(zip(angles, flips)):
        beta = np.radians(beta_deg)
        radial = np.cos(beta) * f.septum + np.sin(beta) * f.e2
        row, col = _rotate_in_plane(-radial if flip else radial, -f.long_axis, la_rot)
        centre = f.apex + centre_z * f.long_axis
        if l_row or l_col:
            centre = centre + l_row * row + l_col * col
        g = _geometry(centre, row, col, n, dx, th)
        out.append(PlannedSlice(VIEW_LA, k, g, f'tagged LA {beta_deg:g}deg', float(beta_deg)))
    return out


def slab_profile(thickness: float, subplanes: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Sub-plane offsets (mm, along the normal) and normalised weights of the slab.

    Gaussian profile with FWHM = ``thickness``, sampled at ``subplanes`` midpoints of
    ``[−0.75, 0.75] · thickness``; one sub-plane means the mid-plane only.

    Returns
    -------
    offsets, weights : ndarray, shape (subplanes,)

    """
    if subplanes < 1:
        raise ValueError(f'subplanes must be >= 1, got {subplanes}')
    if subplanes == 1:
        return np.zeros(1), np.ones(1)
    span = 1.5 * thickness
    off = ((np.arange(subplanes) + 0.5) / subplanes - 0.5) * span
    sigma = thickness / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    w = np.exp(-0.5 * (off / sigma) ** 2)
    return off, w / w.sum()


def plane_centre(geometry: SliceGeometry, shape: tuple[int, int]) -> np.ndarray:
    """Return the patient position of a ``(rows, cols)`` image's centre (tag-grid origin), mm."""
    rows, cols = shape
    return geometry.pixel_to_patient(np.array([(rows - 1) / 2.0, (cols - 1) / 2.0]))


def tag_pattern(
    points: np.ndarray,
    geometry: SliceGeometry,
    shape: tuple[int, int],
    spacing: float,
    angle_deg: float = 0.0,
    lines: str = 'grid',
) -> np.ndarray:
    """
    1-1 SPAMM grid ``P = sin²(π a/λ) sin²(π b/λ)`` of one image plane, in [0, 1].

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Positions (ED material positions for moving tissue), mm.
    geometry : SliceGeometry
        Plane whose tags are evaluated: tag planes ⟂ the image, one family ⟂ each of the row
        and column directions, through the image centre.
    shape : (int, int)
        Image rows, columns (locates the centre).
    spacing : float
        Tag period λ, mm.
    angle_deg : float
        In-plane rotation of the grid from the image axes, degrees (scanners lay the grid at any
        angle; 0 puts the tag planes ⟂ the row and column directions).
    lines : str
        ``'grid'`` (both families) or ``'single'`` (the family ⟂ the turned row direction
        alone: ``P = sin²(π a/λ)``).

    Returns
    -------
    ndarray, shape (N,)
        0 on tag planes, 1 midway between them in both directions.

    Raises
    ------
    ValueError
        ``lines`` is neither ``'grid'`` nor ``'single'``.

    """
    if lines not in ('grid', 'single'):
        raise ValueError(f"tag lines must be 'grid' or 'single', got {lines!r}")
    d = np.asarray(points, dtype=np.float64) - plane_centre(geometry, shape)
    ca, sa = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    u = ca * geometry.row_direction + sa * geometry.column_direction
    v = -sa * geometry.row_direction + ca * geometry.column_direction
    a = d @ u
    if lines == 'single':
        return np.sin(np.pi * a / spacing) ** 2
    b = d @ v
    return (np.sin(np.pi * a / spacing) * np.sin(np.pi * b / spacing)) ** 2


def draw_noise(rng: np.random.Generator, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """
    Draw one image's noise as :meth:`ImageSynthesizer.render` does: two standard normal fields.

    Parameters
    ----------
    rng : numpy.random.Generator
        Drawn from, in this order: the real channel's field, then the imaginary one's.
    shape : tuple of int
        (rows, cols).

    Returns
    -------
    n1, n2 : ndarray of float64, shape ``shape``
        Unit-variance fields (scaled by σ where used).

    """
    return rng.standard_normal(shape), rng.standard_normal(shape)


class ImageSynthesizer:
    """
    Renders the tagged images of one planned slice at any phase.

    Parameters
    ----------
    motion : LVMotion
        Ground-truth motion and ED geometry.
    plane : PlannedSlice
        The slice.
    size : int
        Rows = columns.
    imaging : dict
        The preset's ``imaging`` section (tag spacing, T1, intensities, PSF, slab).
    subplanes : int, optional
        Overrides ``imaging.subplanes``.

    """

    def __init__(
        self,
        motion: LVMotion,
        plane: PlannedSlice,
        size: int,
        imaging: dict,
        subplanes: int | None = None,
    ):
        self.motion = motion
        self.plane = plane
        self.size = n = int(size)
        self.im = imaging
        g = plane.geometry
        self.spacing = float(imaging['tag_spacing_mm'])
        self.tag_angle = float(imaging.get('tag_angle_deg', 0.0))
        self.tag_lines = str(imaging.get('tag_lines', 'grid'))
        self.offsets, self.weights = slab_profile(
            g.slice_thickness, int(subplanes or imaging['subplanes'])
        )
        rr, cc = np.meshgrid(np.arange(n), np.arange(n), indexing='ij')
        pix = g.pixel_to_patient(np.stack([rr.ravel(), cc.ravel()], axis=1))  # (n², 3)
        # Static background: tags at the pixel itself; the same on every sub-plane.
        f = motion.frame
        heart_c = f.apex + 0.5 * motion.length * f.long_axis
        body = np.linalg.norm(pix - heart_c, axis=1) < float(imaging['body_radius_mm'])
        self.bg_m0 = np.where(body, float(imaging['background_m0']), 0.0)
        self.bg_tagged = bool(imaging.get('background_tagged', True))
        self.bg_tags = self._tags(pix) if self.bg_tagged else None
        # Pixels whose slab can meet the LV at any phase: the LV stays inside the cylinder of
        # radius ~1.15 max ED radius (the apical cap widens by 1/sqrt(λ)) up to the atrium top.
        r, _, z = f.to_local(pix)
        reach = np.abs(self.offsets).max()
        zmax = motion.length + motion.atrium_height
        self.cand = np.flatnonzero(
            (r < 1.15 * motion.reach_radius + 3.0 + reach)
            & (z > -3.0 - reach)
            & (z < zmax + 3.0 + reach)
        )
        # Their centres (patient mm, (len(cand), 3)): the whole grid's are not kept (a render
        # process holds every slice's synthesizer at once).
        self.base = pix[self.cand]
        self.normal = g.normal
        self._local = None  # _sub_planes_local()

    def _tags(self, pts):
        return tag_pattern(
            pts,
            self.plane.geometry,
            (self.size, self.size),
            self.spacing,
            self.tag_angle,
            self.tag_lines,
        )

    def _sub_planes_local(self) -> list:
        """
        Return each sub-plane's candidate pixel centres in the LV frame, ``(r, θ, z)`` each.

        The same at every phase: computed on the first render and kept (~0.6 MB a slice of
        the default study).
        """
        if self._local is None:
            f = self.motion.frame
            self._local = [f.to_local(self.base + off * self.normal) for off in self.offsets]
        return self._local

    def tissue_fractions(self, phase) -> tuple[np.ndarray, np.ndarray]:
        """Return slab-weighted myocardium and blood fractions at ``phase``, (rows, cols), 0..1."""
        myo = np.zeros(self.size * self.size)
        blood = np.zeros_like(myo)
        for local, w in zip(self._sub_planes_local(), self.weights):
            X = self.motion.inverse_local(local, phase)
            myo[self.cand] += w * self.motion.inside_myocardium(X)
            blood[self.cand] += w * self.motion.inside_blood(X)
        return myo.reshape(self.size, self.size), blood.reshape(self.size, self.size)

    def render(self, phase, time_s: float, snr: float | None, rng: np.random.Generator | None):
        """
        Image at ``phase`` (trigger time ``time_s``), float32 (rows, cols).

        ``snr`` None or ``inf`` gives the noiseless magnitude image.
        """
        im = self.im
        E = np.exp(-time_s / float(im['t1_s']))
        if self.bg_tagged:
            sig = self.bg_m0 * (E * self.bg_tags + 1.0 - E)  # sub-plane independent
        else:
            sig = self.bg_m0.copy()
        acc = np.zeros(self.base.shape[0])
        m_myo, m_blood = float(im['myocardium_m0']), float(im['blood_m0'])
        bg = sig[self.cand]
        for local, w in zip(self._sub_planes_local(), self.weights):
            X = self.motion.inverse_local(local, phase)
            myo, blood = self.motion.tissue(X)
            val = np.where(blood, m_blood, bg)
            # tagged magnetisation where there is myocardium (the tags evaluated there only)
            val[myo] = m_myo * (E * self._tags(X[myo]) + 1.0 - E)
            acc += w * val
        sig = sig.copy()
        sig[self.cand] = acc
        img = sig.reshape(self.size, self.size)
        psf = float(im.get('psf_sigma_px', 0.0))
        if psf > 0:
            img = gaussian_filter(img, psf, mode='nearest')
        if snr is not None and np.isfinite(snr):
            if snr <= 0:
                raise ValueError(f'snr must be positive (or None/inf for no noise), got {snr}')
            if rng is None:
                raise ValueError('render needs an rng when snr is finite')
            sigma = m_myo / snr
            n1, n2 = draw_noise(rng, img.shape)
            img = np.hypot(img + sigma * n1, sigma * n2)
        return img.astype(np.float32)

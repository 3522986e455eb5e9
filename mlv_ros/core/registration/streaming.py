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
Streaming ED myocardium masks for the tag detector (one frame at a time).

The ``tag_detector`` node must hand :class:`~mlv_ros.core.tags.SliceTracker` a myocardium mask
at ED (phase 0) of every slice, but frames arrive one by one (slice-major: SA 0's whole cine,
SA 1's, …, then LA; or phase-major), so the batch path of :func:`register_ed` (long axis from all
slices first) is not available. :class:`StreamingMasker` keeps what it has seen so far:

* the geometry of every frame (``observe_geometry``): SA normals and positions give the long-axis
  direction, oriented apex → base because SA slice_index 0 is the most basal;
* the blood-pool centre (patient mm) of every SA slice it has segmented: a line through them is
  the long axis.

An SA ED frame is segmented (:func:`.segment.segment_sa`) around the axis intersection when an
axis exists, else around the untagged blood pool found in the image itself (at ED blood has
lost its tags by flow; myocardium is tagged and encloses it). An LA ED frame needs the long
axis: a mid-stack axis point projected into the plane and the axis direction projected into it
(:func:`.segment.segment_la`); without any SA centre it returns ``(None, reason)``. Each slice's
result is kept: asking again for the same frame returns it (and its reason, given once, the
candidates that failed alike grouped) until a new SA centre changes the axis.

Pure numpy/scipy; never raises on image content.
"""

from __future__ import annotations

import hashlib

from mlv_ros.core.registration import segment as seg
from mlv_ros.core.types import Frame, VIEW_LA, VIEW_SA
import numpy as np
from scipy import ndimage as ndi

#: Anatomical prior for apex → base when the SA stack cannot orient the axis (one slice seen):
#: same prior as :func:`mlv_ros.core.io.dicom.estimate_long_axis` (base toward patient right,
#: posterior, head).
_BASE_SIDE = np.array([-1.0, 1.0, 1.0]) / np.sqrt(3.0)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _disk(radius_px: float) -> np.ndarray:
    r = max(int(round(radius_px)), 1)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return x * x + y * y <= r * r


def cavity_centre(s: seg.SliceSegmentation) -> np.ndarray | None:
    """
    Area centroid of the cavity ``ρ < endo(θ)`` of an SA segmentation, (row, col) px.

    Falls back to the epicardial region when there is no cavity (apical slice). The centroid of
    a star-shaped region is ``∫ ρ³/3 (sin θ, cos θ) dθ / ∫ ρ²/2 dθ`` around the ray origin.

    Returns
    -------
    ndarray, shape (2,) or None
        None when the segmentation holds no usable contour.

    """
    for r in (s.endo, s.epi):
        r = np.nan_to_num(np.asarray(r, dtype=np.float64))
        area = np.sum(r**2) / 2.0
        if r.size and area > 1.0:
            d = np.array([np.sum(r**3 * np.sin(s.angles)), np.sum(r**3 * np.cos(s.angles))]) / 3.0
            return np.asarray(s.centre_rc, dtype=np.float64) + d / area
    return None


def _finite_features(img: np.ndarray, sp: float, families: int = 2) -> list:
    """
    Return the :func:`.segment.candidate_features` with finite energy and period.

    Both spectral estimates (a bright RV pool beside the wall can mislead the plain one), the plain
    one first (the blood-pool search uses it); empty when none is finite. ``families``: tag
    directions in the image (2: a grid, 1: one family of tag lines).
    """
    return [
        f
        for f in seg.candidate_features(img, pixel_spacing_mm=sp, families=families)
        if np.all(np.isfinite(f.energy)) and np.isfinite(f.wavelength_px)
    ]


def blood_pool_candidates(
    feat: seg.TagFeatures, pixel_spacing_mm: float, max_candidates: int = 3
) -> list[np.ndarray]:
    """
    Likely LV blood-pool centres of an ED tagged image, best first, (row, col) px.

    Blood is untagged (low tag energy) at ED, whatever its brightness. Untagged components are
    ranked by how much of a ring just outside them is tagged (the myocardium encloses the LV
    cavity), by a plausible area, by closeness to the field-of-view centre (where the heart is
    planned) and by a mean intensity above the darkest untagged tissue (air and lung are near
    the noise floor; blood is not). Components touching the image border are not cavities (the
    dark surroundings of a study that tags only the heart, air outside the body).

    Parameters
    ----------
    feat : TagFeatures
        From :func:`.segment.tag_features`.
    pixel_spacing_mm : float
        In-plane pixel size, mm (sets the ring widths and the plausible area in pixels).
    max_candidates : int
        Most centres returned.

    Returns
    -------
    list of ndarray, shape (2,)
        Possibly empty.

    """
    e, m = feat.energy, feat.mean
    ok = np.isfinite(e) & np.isfinite(m)
    if ok.sum() < 100:
        return []
    pos = ok & (e > 0)
    if pos.sum() < 20:
        return []
    thr = seg._otsu(e[pos])
    hi = pos & (e > thr)
    if hi.sum() < 20:
        return []
    e_tag, m_tag = float(np.median(e[hi])), float(np.median(m[hi]))
    untagged = ok & (e < 0.25 * e_tag)
    # Opening removes untagged speckle between tag lines in noisy tissue.
    blood = ndi.binary_opening(untagged, structure=_disk(2.0 / pixel_spacing_mm))
    lab, n = ndi.label(blood)
    if n == 0:
        return []
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    # Darkest untagged level: the noise floor where there is air, else the darkest tissue.
    m_dark = float(np.percentile(m[untagged], 5)) if untagged.sum() >= 20 else 0.0
    px_area = pixel_spacing_mm**2
    rows, cols = e.shape
    fov_c = np.array([(rows - 1) / 2.0, (cols - 1) / 2.0])
    fov_r = 0.5 * min(rows, cols)
    tagged = ok & (e > 0.5 * e_tag)
    near = _disk(1.5 / pixel_spacing_mm)
    far = _disk(6.0 / pixel_spacing_mm)
    scored = []
    for i, sl in enumerate(ndi.find_objects(lab), start=1):
        if i in border:
            continue
        area_mm2 = float(np.sum(lab[sl] == i)) * px_area
        # LV cavity at ED: ~ 10 mm² (apex) to ~ 5000 mm² (dilated base); reject specks and
        # anything as large as the background.
        if area_mm2 < 20.0 or area_mm2 > 8000.0:
            continue
        pad = int(np.ceil(7.0 / pixel_spacing_mm)) + 1
        box = tuple(slice(max(s.start - pad, 0), s.stop + pad) for s in sl)
        comp = lab[box] == i
        ring = ndi.binary_dilation(comp, far) & ~ndi.binary_dilation(comp, near)
        if ring.sum() == 0:
            continue
        enclosed = float(tagged[box][ring].mean())
        c = np.array(ndi.center_of_mass(comp)) + np.array([b.start for b in box])
        dist = np.linalg.norm(c - fov_c) / fov_r
        # Blood stands above the darkest untagged tissue by a fair share of the tagged mean.
        m_comp = float(np.median(m[box][comp]))
        bright = float(
            np.clip((m_comp - m_dark) / max(0.5 * abs(m_tag - m_dark), 1e-300), 0.0, 1.0)
        )
        scored.append((enclosed * bright * np.exp(-0.5 * (dist / 0.5) ** 2), c))
    scored.sort(key=lambda t: -t[0])
    return [c for s, c in scored[:max_candidates] if s > 0.05]


def _grouped(reasons: list[tuple[str, str]]) -> str:
    """Join ``[(a, why), (b, why), (c, other)]`` as ``"a, b: why; c: other"``: each reason once."""
    by_reason: dict = {}
    for how, why in reasons:
        by_reason.setdefault(why, []).append(how)
    return '; '.join(f'{", ".join(dict.fromkeys(hows))}: {why}' for why, hows in by_reason.items())


class StreamingMasker:
    """
    Automatic ED myocardium masks for frames that arrive one at a time.

    Hold one per acquisition. Call :meth:`observe_geometry` for every frame seen (cheap), and
    :meth:`ed_mask` for each ED (phase 0) frame. SA frames are self-sufficient (the first one
    uses an image-based blood-pool estimate); each successful SA segmentation adds its blood-pool
    centre to the long-axis estimate that later SA slices and all LA frames use.

    Parameters
    ----------
    max_plane_offset_mm : float
        LA: reject when the mid-stack axis point lies farther than this from the LA plane (the
        plane does not contain the long axis).
    axis_tilt_max_deg : float
        Largest tilt of the fitted centre line from the SA normal; beyond it the fit is
        clipped (centres from a few slices are noisy, and SA stacks are planned roughly
        perpendicular to the long axis).
    max_axis_jump_mm : float
        SA: when the cavity found from the axis intersection lies farther than this from it,
        the image-based blood-pool centres are tried first (that result is the fallback).

    Examples
    --------
    >>> masker = StreamingMasker()
    >>> for f in frames:                       # any order; one frame at a time
    ...     masker.observe_geometry(f)
    ...     mask, why = masker.ed_mask(f) if f.phase_index == 0 else (None, "")

    """

    def __init__(
        self,
        *,
        max_plane_offset_mm: float = 15.0,
        axis_tilt_max_deg: float = 25.0,
        max_axis_jump_mm: float = 12.0,
    ):
        self.max_plane_offset_mm = float(max_plane_offset_mm)
        self.max_axis_jump_mm = float(max_axis_jump_mm)
        self.axis_tilt_max_deg = float(axis_tilt_max_deg)
        self._sa_geom: dict = {}  # slice_index -> SliceGeometry
        self._la_geom: dict = {}
        self._sa_centre: dict = {}  # slice_index -> blood-pool centre, patient mm (3,)
        self._results: dict = {}  # (view, slice_index) -> (fingerprint, mask or None, reason)
        self._failures: dict = {}  # (view, slice_index) -> reason of its latest failure

    # ------------------------------------------------------------------ state
    def observe_geometry(self, frame: Frame) -> None:
        """Record the plane of a frame (any phase). Ignores frames without usable geometry."""
        try:
            view, idx, g = int(frame.view), int(frame.slice_index), frame.geometry
            _ = g.normal
        except Exception:  # malformed record: nothing to learn from it
            return
        if view == VIEW_SA:
            self._sa_geom[idx] = g
        elif view == VIEW_LA:
            self._la_geom[idx] = g

    @property
    def sa_centres(self) -> dict:
        """Blood-pool centres found so far, ``{slice_index: (3,) mm}`` (a copy)."""
        return {k: v.copy() for k, v in self._sa_centre.items()}

    def axis_direction(self) -> tuple[np.ndarray, bool] | None:
        """
        SA-stack normal oriented apex → base.

        Returns
        -------
        (ndarray (3,), bool) or None
            Unit direction and whether its sign is known from ≥ 2 SA slices (else the
            anatomical prior orients it). None before any SA geometry.

        """
        if not self._sa_geom:
            return None
        idx = sorted(self._sa_geom)
        ns = np.array([self._sa_geom[i].normal for i in idx])
        ns = ns * np.sign(ns @ ns[0])[:, None]
        d = _unit(ns.mean(axis=0))
        lo, hi = self._sa_geom[idx[0]], self._sa_geom[idx[-1]]
        sep = float((lo.image_position - hi.image_position) @ d)
        if len(idx) >= 2 and abs(sep) > 1e-3:
            # slice_index 0 is the most basal: the lowest index lies toward the base.
            return (d if sep > 0 else -d), True
        return (d if d @ _BASE_SIDE >= 0 else -d), False

    def long_axis(self) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """
        Long axis through the SA blood-pool centres found so far.

        Returns
        -------
        (point (3,), direction (3,), sign_known) or None
            ``point`` lies at the middle of the observed SA stack; ``direction`` is unit,
            apex → base. None before any SA centre.

        """
        dd = self.axis_direction()
        if dd is None or not self._sa_centre:
            return None
        d, known = dd
        idx = sorted(self._sa_centre)
        P = np.array([self._sa_centre[i] for i in idx])
        z = P @ d
        zc = float(np.mean([g.image_position @ d for g in self._sa_geom.values()]))
        if len(idx) >= 2 and np.ptp(z) > 1.0:
            keep = np.ones(len(z), bool)
            for _ in range(2):
                a, b, zm = self._fit_line(P[keep], z[keep], d)
                # One misplaced centre (a cavity far off the others) must not bend the axis.
                res = np.linalg.norm(P - np.outer(z, d) - a - np.outer(z - zm, b), axis=1)
                new = res <= max(self.max_axis_jump_mm, 2.0 * float(np.median(res)))
                if keep.sum() < 3 or new.sum() < 2 or np.array_equal(new, keep):
                    break
                keep = new
            direction = _unit(d + b)
            point = a + b * (zc - zm) + zc * d
        else:
            direction = d
            point = P.mean(axis=0) + (zc - float(P.mean(axis=0) @ d)) * d
        return point, direction, known

    def _fit_line(self, P: np.ndarray, z: np.ndarray, d: np.ndarray):
        """
        Fit an in-plane offset linear in z: x⊥(z) = a + b (z − z̄).

        A ridge toward b = 0 keeps a two-slice fit from swinging the axis, and the tilt is clipped.
        """
        zm = float(z.mean())
        Q = P - np.outer(z, d)
        A = np.stack([np.ones_like(z), z - zm], 1)
        lam = np.diag([0.0, 0.1 * len(z) * 25.0])  # ~ one 5-mm slice worth of prior
        coef = np.linalg.solve(A.T @ A + lam, A.T @ Q)
        a, b = coef[0], coef[1]
        b = b - (b @ d) * d
        tmax = np.tan(np.radians(self.axis_tilt_max_deg))
        if np.linalg.norm(b) > tmax:
            b = b * tmax / np.linalg.norm(b)
        return a, b, zm

    # ------------------------------------------------------------------ masks
    def ed_mask(self, frame: Frame) -> tuple[np.ndarray | None, str]:
        """
        Myocardium mask of an ED frame from what has been observed so far.

        The result is kept per slice: the same frame asked for again, while no SA centre has
        been added since, returns it without segmenting again (a copy of the mask), so a slice
        that cannot be segmented gives its reason once, not once per request. :attr:`failures`
        holds the reasons of the slices whose latest ED frame failed.

        Parameters
        ----------
        frame : Frame
            Phase-0 frame of an SA or LA slice (its geometry is observed here too).

        Returns
        -------
        mask : ndarray of bool, shape (rows, cols), or None
        reason : str
            ``""`` on success (or a short note on how the centre was found), else why not.

        """
        try:
            self.observe_geometry(frame)
            key = (int(frame.view), int(frame.slice_index))
            stamp = self._fingerprint(frame)
            cached = self._results.get(key)
            if cached is not None and stamp is not None and cached[0] == stamp:
                mask, why = cached[1], cached[2]
                return (None if mask is None else mask.copy()), why
            mask, why = self._ed_mask(frame)
            self._results[key] = (stamp, mask, why)
            if mask is None:
                self._failures[key] = why
            else:
                self._failures.pop(key, None)
            return (None if mask is None else mask.copy()), why
        except Exception as exc:  # never let one image stop the detector
            return None, f'segmentation failed ({type(exc).__name__}: {exc})'

    @property
    def failures(self) -> dict:
        """``{(view, slice_index): reason}`` of the slices whose latest ED frame gave no mask."""
        return dict(self._failures)

    def _fingerprint(self, frame: Frame):
        """
        Return what the result of :meth:`ed_mask` depends on; None when the frame cannot be hashed.

        The frame (indices, geometry, image bytes) and the SA centres found so far.
        """
        try:
            img = np.ascontiguousarray(frame.image)
            g = frame.geometry
            digest = hashlib.blake2b(img.tobytes(), digest_size=16).hexdigest()
            geo = np.concatenate(
                [
                    np.ravel(g.image_position),
                    np.ravel(g.row_direction),
                    np.ravel(g.column_direction),
                    [g.row_spacing, g.column_spacing],
                ]
            )
            centres = tuple((i, tuple(np.round(c, 6))) for i, c in sorted(self._sa_centre.items()))
            return (
                int(frame.phase_index),
                img.shape,
                str(img.dtype),
                digest,
                tuple(np.round(geo, 9)),
                centres,
            )
        except Exception:  # malformed record: no caching
            return None

    def _ed_mask(self, frame: Frame) -> tuple[np.ndarray | None, str]:
        img = np.asarray(frame.image, dtype=np.float64)
        if img.ndim != 2 or min(img.shape) < 16:
            return None, f'image must be 2-D and at least 16x16 pixels, got shape {img.shape}'
        if not np.all(np.isfinite(img)):
            return None, 'image has non-finite (NaN/inf) pixels'
        if float(img.std()) == 0.0:
            return None, 'image is constant (no signal)'
        g = frame.geometry
        sp = float(g.row_spacing)
        if abs(g.row_spacing - g.column_spacing) > 1e-3 * sp:
            return None, 'anisotropic pixel spacing is not supported'
        if int(frame.view) == VIEW_SA:
            return self._sa(frame, img, sp)
        if int(frame.view) == VIEW_LA:
            return self._la(frame, img, sp)
        return None, f'unknown view {frame.view!r}'

    def _sa(self, frame: Frame, img: np.ndarray, sp: float):
        g = frame.geometry
        feats = _finite_features(img, sp, seg.tag_families(frame.tag_lines))
        if not feats:
            return None, 'no tag pattern found (tag features not finite)'
        feat = feats[0]
        cands: list[tuple[str, np.ndarray]] = []
        ax = self.long_axis()
        if ax is not None:
            p, d, _ = ax
            den = float(d @ g.normal)
            if abs(den) > 0.2:
                x = p + float((g.image_position - p) @ g.normal) / den * d
                cands.append(('long axis', g.patient_to_pixel(x)[0]))
        cands += [('blood pool', c) for c in blood_pool_candidates(feat, sp)]
        rows, cols = img.shape
        cands.append(('image centre', np.array([(rows - 1) / 2.0, (cols - 1) / 2.0])))
        reasons: list[tuple[str, str]] = []
        fallback = None
        for how, c in cands:
            s = seg.segment_sa(img, c, sp, features=feats)
            if not s.ok:
                reasons.append((how, s.reason))
                continue
            # Re-centre on the cavity: rays from the middle of the annulus meet the wall
            # square-on, and the centre feeds the long-axis estimate.
            cc = cavity_centre(s)
            if cc is not None and np.linalg.norm(cc - c) > 1.0:
                s2 = seg.segment_sa(img, cc, sp, features=feats)
                if s2.ok:
                    s = s2
                    cc2 = cavity_centre(s2)
                    cc = cc2 if cc2 is not None else cc
            if cc is None or not s.mask.any():
                reasons.append((how, 'empty myocardium'))
                continue
            if how == 'long axis' and np.linalg.norm(cc - c) * sp > self.max_axis_jump_mm:
                # The axis extrapolated from other slices missed this cavity: prefer an
                # image-based centre, keep this result as a fallback.
                fallback = fallback or (s, cc)
                reasons.append((how, f'cavity {np.linalg.norm(cc - c) * sp:.0f} mm from the axis'))
                continue
            self._sa_centre[int(frame.slice_index)] = g.pixel_to_patient(cc)
            return s.mask, ''
        if fallback is not None:
            self._sa_centre[int(frame.slice_index)] = g.pixel_to_patient(fallback[1])
            return fallback[0].mask, 'cavity far from the long axis of the other slices'
        return None, 'no SA myocardial annulus found (' + _grouped(reasons) + ')'

    def _la(self, frame: Frame, img: np.ndarray, sp: float):
        ax = self.long_axis()
        if ax is None:
            return None, (
                'long axis unknown: no SA slice segmented yet (LA masks need the SA '
                'blood-pool centres; send SA ED frames first)'
            )
        p, d, known = ax
        g = frame.geometry
        axis_rc = np.array([d @ g.column_direction, d @ g.row_direction])
        if np.linalg.norm(axis_rc) < 0.8:
            return None, (
                f'LA plane is not parallel to the long axis (in-plane cos '
                f'{np.linalg.norm(axis_rc):.2f})'
            )
        centre_rc, off = g.patient_to_pixel(p)
        if abs(float(off)) > self.max_plane_offset_mm:
            return None, f'LA plane is {abs(float(off)):.1f} mm from the long axis'
        feats = _finite_features(img, sp, seg.tag_families(frame.tag_lines))
        if not feats:
            return None, 'no tag pattern found (tag features not finite)'
        # Axis point: mid stack first; then toward the apex (a basal point can sit in the
        # open atrial end) and the base. An unknown sign (one SA slice) tries both directions.
        signs = (1.0,) if known else (1.0, -1.0)
        reasons = []
        for sgn in signs:
            a_rc = sgn * axis_rc / np.linalg.norm(axis_rc)
            for shift_mm in (0.0, -10.0, 10.0):
                c = centre_rc + a_rc * shift_mm / sp
                s = seg.segment_la(img, c, a_rc, sp, features=feats)
                if s.ok and s.mask.any():
                    return s.mask, ''
                where = f'axis point {shift_mm:+g} mm' + (
                    '' if known else f' (axis sign {sgn:+g})'
                )
                reasons.append((where, s.reason or 'empty mask'))
        return None, 'no LA horseshoe found (' + _grouped(reasons) + ')'

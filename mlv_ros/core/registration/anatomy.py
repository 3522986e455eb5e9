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
Septum from the images: the RV blood pool next to the LV and its insertion points.

The AHA segments' circumferential origin is the anterior RV–LV insertion (Cerqueira et al.,
Circulation 2002). Without it the only orientation is an anatomical prior (the septum toward
the patient's right, :func:`~mlv_ros.core.registration.initialise.default_reference`), which is
wrong by however far a heart or an acquisition turns. This module finds the septum in the ED
short-axis images instead.

Per SA slice (its LV segmentation :class:`~mlv_ros.core.registration.segment.SliceSegmentation`)
-------------------------------------------------------------------------------------------
* Blood looks like the LV's own cavity: the same mean and no tag texture (flow washes the tags
  out of blood, tagged tissue keeps them). With local mean ``μ`` and local standard deviation
  ``σ`` over a Gaussian window of ``σ_w`` = a quarter of the slice's median wall thickness (≥ 1
  px: a window that sees a tag period wherever tags resolve the wall), a pixel is *blood-like*
  when ``|μ − μ_c| ≤ max(3 s_c, BLOOD_MEAN_TOLERANCE · μ_c)`` and ``σ ≤ σ_c + ½ (σ_wall − σ_c)``,
  with ``μ_c``, ``s_c`` (1.4826 MAD), ``σ_c`` the cavity core's (inside 0.6 × the endocardial
  radius) and ``σ_wall`` the wall's median texture. Every threshold is the slice's own
  statistics: no pixel size, contrast or intensity scale enters.
* The RV is the connected blood-like region outside the LV (the LV and ``2 σ_w`` beyond its
  epicardium excluded) reached by the most rays within a band ``2 σ_w + ½ R_epi`` beyond the
  epicardium (``R_epi`` the slice's median epicardial radius), with an area of at least
  ``MIN_RV_AREA`` × the LV cavity's.
* Its arc is the longest circular run of rays that reach it; the run's ends are the insertion
  points (blood tapers to nothing there, so the detected arc is a little short of the true one:
  the bisector, which is what orients the segments, is not biased by it). A slice counts when
  its arc spans ``ARC_RANGE_DEG`` (an RV wraps part of the LV, never none or all of it).

Across slices
-------------
The slices' septum directions (bisectors, projected ⟂ the long axis) are averaged on the circle;
slices more than ``OUTLIER_DEG`` from the mean are dropped and the mean recomputed. The septum
is *detected* when at least ``MIN_SLICES`` slices and ``MIN_SLICE_FRACTION`` of the segmented SA
slices agree with a mean resultant length ≥ ``MIN_AGREEMENT`` (a circular spread of about 25°);
otherwise the anatomical prior is kept and the result says so (``source = "prior"`` and why).
``confidence`` = agreement × share of the segmented SA slices that found the RV, in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from mlv_ros.core.registration.segment import polar_mask, SliceSegmentation
import numpy as np
from scipy import ndimage

#: A blood-like pixel's local mean may differ from the LV cavity's by this share of it (or 3 of
#: the cavity's own spreads, whichever is larger): same blood, same signal, up to coil shading.
BLOOD_MEAN_TOLERANCE = 0.25
#: The RV blood pool covers at least this share of the slice's LV cavity area.
MIN_RV_AREA = 0.1
#: Plausible arc of the LV circumference the RV wraps, degrees.
ARC_RANGE_DEG = (40.0, 220.0)
#: A slice's septum farther than this from the slices' mean is an outlier, degrees.
OUTLIER_DEG = 45.0
#: Agreement needed to use the detected septum (mean resultant length of the slices' septa).
MIN_AGREEMENT = 0.9
MIN_SLICES = 2
MIN_SLICE_FRACTION = 1.0 / 3.0

SOURCE_PRIOR = 'prior'
SOURCE_DETECTED = 'detected'
SOURCE_GIVEN = 'given'


@dataclass
class SliceRV:
    """
    The RV found on one SA slice.

    Attributes
    ----------
    start, end : int
        Ray indices of the arc's ends (the arc runs start → end with increasing ray index,
        circularly).
    arc_deg : float
        Arc between the insertion points, degrees.
    area_px : int
        Pixels of the RV blood region.
    mask : ndarray of bool
        The RV blood region.

    """

    start: int
    end: int
    arc_deg: float
    area_px: int
    mask: np.ndarray


@dataclass
class SeptumEstimate:
    """
    Where the septum is, and how it was known.

    Attributes
    ----------
    source : str
        ``"detected"`` (RV insertion points in the images), ``"prior"`` (patient's right,
        :func:`~mlv_ros.core.registration.initialise.default_reference`) or ``"given"`` (the
        caller's reference direction).
    septum : ndarray, shape (3,)
        Unit mid-septum direction ⟂ the long axis, LPS.
    anterior, inferior : ndarray, shape (3,) or None
        Unit directions of the anterior / inferior RV insertion (detected only).
    span_deg : float
        Angle between the insertions, degrees (NaN with the prior).
    confidence : float
        0 … 1 (module docstring); 0 with the prior.
    slices_found, slices_used, slices_total : int
        SA slices where an RV was found, that agreed, and that were segmented.
    reason : str
        Why the prior was kept ('' when detected).

    """

    source: str
    septum: np.ndarray
    anterior: np.ndarray | None = None
    inferior: np.ndarray | None = None
    span_deg: float = float('nan')
    confidence: float = 0.0
    slices_found: int = 0
    slices_used: int = 0
    slices_total: int = 0
    reason: str = ''
    per_slice: list = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-friendly summary."""

        def vec(v):
            return None if v is None else [round(float(x), 6) for x in v]

        return {
            'source': self.source,
            'septum_direction': vec(self.septum),
            'anterior_insertion_direction': vec(self.anterior),
            'inferior_insertion_direction': vec(self.inferior),
            'span_deg': None if not np.isfinite(self.span_deg) else round(float(self.span_deg), 1),
            'confidence': round(float(self.confidence), 3),
            'slices_found': self.slices_found,
            'slices_used': self.slices_used,
            'slices_total': self.slices_total,
            'reason': self.reason,
        }


def _local_stats(image: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    img = np.asarray(image, dtype=np.float64)
    mu = ndimage.gaussian_filter(img, sigma, mode='nearest')
    var = ndimage.gaussian_filter(img * img, sigma, mode='nearest') - mu * mu
    return mu, np.sqrt(np.clip(var, 0.0, None))


def _longest_run(hit: np.ndarray) -> tuple[int, int, int]:
    """Longest circular run of True: (start, end, length); length 0 when none, n when all."""
    n = hit.size
    if not hit.any():
        return 0, 0, 0
    if hit.all():
        return 0, n - 1, n
    roll = int(np.flatnonzero(~hit)[0])  # start the scan just after a miss
    h = np.roll(hit, -roll)
    best = (0, 0, 0)
    i = 0
    while i < n:
        if h[i]:
            j = i
            while j + 1 < n and h[j + 1]:
                j += 1
            if j - i + 1 > best[2]:
                best = ((i + roll) % n, (j + roll) % n, j - i + 1)
            i = j + 1
        else:
            i += 1
    return best


def find_rv(image: np.ndarray, seg: SliceSegmentation) -> tuple[SliceRV | None, str]:
    """
    Find the RV blood pool next to the LV on one ED SA slice (module docstring).

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        The slice's ED image (any intensity scale).
    seg : SliceSegmentation
        Its LV segmentation (``ok``, SA).

    Returns
    -------
    (SliceRV or None, str)
        The RV, or None and why not.

    """
    img = np.asarray(image, dtype=np.float64)
    if not seg.ok or seg.angles.size < 8:
        return None, 'no LV segmentation'
    endo, epi = np.asarray(seg.endo, float), np.asarray(seg.epi, float)
    good = np.isfinite(epi) & np.isfinite(endo) & (epi > endo) & (endo > 0)
    if good.sum() < 0.5 * epi.size:
        return None, 'no cavity on most rays'
    wall = float(np.median((epi - endo)[good]))
    r_epi = float(np.median(epi[good]))
    sigma = max(1.0, 0.25 * wall)
    endo_f = np.where(good, endo, np.nanmedian(endo[good]))
    epi_f = np.where(np.isfinite(epi), epi, r_epi)
    blood = _blood_outside_lv(img, seg, endo_f, epi_f, sigma)
    if isinstance(blood, str):
        return None, blood
    labels, n = ndimage.label(blood)
    if n == 0:
        return None, 'no blood-like region outside the LV'
    # Which region each ray meets first within the band beyond the epicardium.
    lab = _labels_beyond(labels, seg, epi_f, 2.0 * sigma + 0.5 * r_epi)
    cavity_area = float(np.pi * np.median(endo[good]) ** 2)
    areas = ndimage.sum(np.ones_like(labels), labels, index=np.arange(1, n + 1))
    best, best_rays = 0, 0
    for k in range(1, n + 1):
        if areas[k - 1] < MIN_RV_AREA * cavity_area:
            continue
        rays = int(np.any(lab == k, axis=1).sum())
        if rays > best_rays:
            best, best_rays = k, rays
    if best == 0:
        return None, 'no blood region next to the LV as large as a tenth of its cavity'
    hit = np.any(lab == best, axis=1)
    start, end, length = _longest_run(hit)
    step_deg = 360.0 / seg.angles.size
    arc = length * step_deg
    if not ARC_RANGE_DEG[0] <= arc <= ARC_RANGE_DEG[1]:
        lo, hi = ARC_RANGE_DEG
        return None, f'the blood next to the LV wraps {arc:.0f}° of it (an RV: {lo:g}–{hi:g}°)'
    return SliceRV(start, end, arc, int(areas[best - 1]), labels == best), ''


def _blood_outside_lv(img, seg, endo_f, epi_f, sigma):
    """
    Pixels outside the LV that look like its cavity's blood, bool (rows, cols), or why not.

    Blood: the local mean near the cavity's and the local texture (tags) below half-way from
    the cavity's to the wall's, both measured on this slice (scale σ px).
    """
    mu, sd = _local_stats(img, sigma)
    c = seg.centre_rc
    core = polar_mask(img.shape, c, seg.angles, np.zeros_like(endo_f), 0.6 * endo_f) & ~seg.mask
    core &= polar_mask(
        img.shape, c, seg.angles, np.zeros_like(endo_f), np.maximum(endo_f - 2 * sigma, 0.0)
    )
    wall_px = (
        seg.mask
        & ~polar_mask(img.shape, c, seg.angles, endo_f, endo_f + sigma)
        & ~polar_mask(img.shape, c, seg.angles, np.maximum(epi_f - sigma, 0.0), epi_f)
    )
    if core.sum() < 9 or wall_px.sum() < 9:
        return 'LV cavity or wall too small to take blood statistics from'
    mu_c = float(np.median(mu[core]))
    s_c = 1.4826 * float(np.median(np.abs(mu[core] - mu_c)))
    sd_c = float(np.median(sd[core]))
    sd_w = float(np.median(sd[wall_px]))
    if not sd_w > sd_c:
        return 'the wall shows no more texture than the blood (no tags to tell them apart)'
    blood = (np.abs(mu - mu_c) <= max(3.0 * s_c, BLOOD_MEAN_TOLERANCE * abs(mu_c))) & (
        sd <= sd_c + 0.5 * (sd_w - sd_c)
    )
    lv = polar_mask(img.shape, c, seg.angles, np.zeros_like(epi_f), epi_f + 2.0 * sigma)
    return blood & ~lv


def _labels_beyond(labels, seg, epi_f, band):
    """Region labels along each ray from the epicardium out to ``band`` px, (rays, samples)."""
    c = seg.centre_rc
    shape = labels.shape
    steps = np.arange(0.0, band + 1e-9, 0.5)
    dirs = np.stack([np.sin(seg.angles), np.cos(seg.angles)], 1)
    rr = c[0] + (epi_f[:, None] + steps[None, :]) * dirs[:, 0, None]
    cc = c[1] + (epi_f[:, None] + steps[None, :]) * dirs[:, 1, None]
    inside = (rr >= 0) & (rr <= shape[0] - 1) & (cc >= 0) & (cc <= shape[1] - 1)
    return np.where(
        inside,
        labels[
            np.clip(np.rint(rr).astype(int), 0, shape[0] - 1),
            np.clip(np.rint(cc).astype(int), 0, shape[1] - 1),
        ],
        0,
    )


def _ray_direction(geometry, centre_rc, angle, axis) -> np.ndarray:
    """Return the unit direction ⟂ ``axis`` of the in-plane ray at ``angle`` from ``centre_rc``."""
    d = np.array([math.sin(angle), math.cos(angle)])
    v = geometry.pixel_to_patient(centre_rc + d) - geometry.pixel_to_patient(centre_rc)
    v = np.asarray(v, float).reshape(-1)
    v = v - (v @ axis) * axis
    return v / np.linalg.norm(v)


def estimate_septum(slices, axis, prior) -> SeptumEstimate:
    """
    Find the septum from the ED SA slices, or the prior when they do not agree (module docstring).

    Parameters
    ----------
    slices : list of (image, SliceSegmentation, SliceGeometry)
        The segmented ED SA slices.
    axis : array_like, shape (3,)
        Unit long axis apex → base, LPS.
    prior : array_like, shape (3,)
        The anatomical prior's mid-septum direction (kept when detection fails).

    Returns
    -------
    SeptumEstimate

    """
    axis = np.asarray(axis, float)
    axis = axis / np.linalg.norm(axis)
    p = np.asarray(prior, float)
    p = p - (p @ axis) * axis
    p = p / np.linalg.norm(p)
    e2 = np.cross(p, axis)  # θ grows CCW seen from the apex (mlv_ros.core.analysis.frame)

    found, reasons = _rv_insertions(slices, axis, p, e2)
    total = len(slices)
    est = SeptumEstimate(
        SOURCE_PRIOR,
        p,
        slices_found=len(found),
        slices_total=total,
        per_slice=[
            {'anterior_deg': math.degrees(f[0]), 'inferior_deg': math.degrees(f[1])} for f in found
        ],
    )
    if not found:
        common = max(set(reasons), key=reasons.count) if reasons else 'no segmented SA slice'
        est.reason = f'no RV found on any SA slice ({common})'
        return est
    mids = np.array([f[2] for f in found])
    mean, keep, agreement = _agreeing_mean(mids)
    used = int(keep.sum())
    est.slices_used = used
    need = max(MIN_SLICES, math.ceil(MIN_SLICE_FRACTION * total))
    if used < need or agreement < MIN_AGREEMENT:
        est.reason = (
            f'an RV was found on {len(found)} of {total} SA slices, {used} agreeing '
            f'(agreement {agreement:.2f}; need {need} slices and {MIN_AGREEMENT:g})'
        )
        return est
    half = 0.5 * float(np.median([f[3] for f, k in zip(found, keep) if k]))

    def direction(t):
        return math.cos(t) * p + math.sin(t) * e2

    est.source = SOURCE_DETECTED
    est.septum = direction(mean)
    est.anterior, est.inferior = direction(mean - half), direction(mean + half)
    est.span_deg = math.degrees(2.0 * half)
    est.confidence = agreement * used / max(total, 1)
    return est


def _rv_insertions(slices, axis, p, e2):
    """
    Each slice's RV insertions, ``(anterior θ, inferior θ, bisector θ, span)`` rad, or why not.

    θ is measured from ``p`` toward ``e2`` about ``axis``; returns ``(found, reasons)``.
    """
    def theta(v):
        return math.atan2(float(v @ e2), float(v @ p))

    found, reasons = [], []
    for image, seg, geom in slices:
        rv, why = find_rv(image, seg)
        if rv is None:
            reasons.append(why)
            continue
        a = seg.angles
        mid_idx = (rv.start + (rv.end - rv.start) % a.size / 2.0) % a.size
        t_s = theta(_ray_direction(geom, seg.centre_rc, a[rv.start], axis))
        t_e = theta(_ray_direction(geom, seg.centre_rc, a[rv.end], axis))
        step = a[1] - a[0]
        t_m = theta(_ray_direction(geom, seg.centre_rc, a[0] + mid_idx * step, axis))

        def wrap(x):
            return (x + math.pi) % (2 * math.pi) - math.pi

        if wrap(t_m - t_s) < 0:  # the rays run clockwise seen from the apex on this slice
            t_s, t_e = t_e, t_s
        # θ counter-clockwise from the anterior to the inferior insertion, bisector between them.
        span = (t_e - t_s) % (2 * math.pi)
        found.append((t_s, t_e, t_s + 0.5 * span, span))
    return found, reasons


def _agreeing_mean(mids: np.ndarray):
    """Circular mean of the bisectors within OUTLIER_DEG of the first mean, (mean, keep, R)."""
    mean = math.atan2(np.sin(mids).mean(), np.cos(mids).mean())
    keep = np.abs(np.angle(np.exp(1j * (mids - mean)))) <= math.radians(OUTLIER_DEG)
    if keep.any():
        mean = math.atan2(np.sin(mids[keep]).mean(), np.cos(mids[keep]).mean())
    agreement = (
        float(np.hypot(np.sin(mids[keep]).mean(), np.cos(mids[keep]).mean()))
        if keep.any()
        else 0.0
    )
    return mean, keep, agreement

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
Tag-grid parameters from the image spectrum and a complex Gabor filter bank.

Conventions (used by the whole :mod:`mlv_ros.core.tags` package)
----------------------------------------------------------------
* Pixel coordinates are ``(row, col)``; vectors such as wave vectors are stored in that order.
* A tag *direction* ``d`` is described by the angle ``theta_d`` of its wave vector (the normal to
  its tag lines) measured from the column axis toward the row axis, in radians, folded into
  ``[0, π)``: the unit wave vector is ``(sin θ, cos θ)`` in ``(row, col)`` order.
* The tag *spacing* ``λ`` is the distance between neighbouring tag lines of one direction, px.
* For a 1-1 SPAMM grid, intensity ∝ sin²(k₁·x/2) sin²(k₂·x/2) = ¼(1 − cos k₁·x)(1 − cos k₂·x):
  each direction contributes ``−¼ cos(k·x)``, so the complex Gabor response ``R`` tuned to that
  direction has phase ``k·x + π``: **phase ≡ π on the centre of a dark tag line**.

References
----------
Chen, T., Wang, X., Chung, S., Metaxas, D., Axel, L. "Automated 3D motion tracking using Gabor
filter bank, robust point matching, and deformable models." IEEE TMI 29(1):1–11, 2010.

"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np
from scipy import ndimage as ndi
import scipy.fft as sfft

# Spacing search range, px: below 3 px the tags are not resolved (Nyquist is 2 px); clinical
# grids are 5–10 mm at 1–2 mm pixels, and longer periods collide with anatomy (wall, cavity).
MIN_SPACING_PX = 3.0
MAX_SPACING_PX = 24.0
# A spectral peak must stand this many times above the median spectral magnitude of the search
# annulus; white noise alone tops out near 4–5 for a 256² image.
MIN_PEAK_RATIO = 8.0
# SPAMM/CSPAMM grid periods in use across vendors and field strengths, mm: finer grids are not
# resolved by cine matrices, coarser ones leave too few intersections across a wall. The tag
# detector and the ED segmentation both search this band.
TAG_PERIOD_RANGE_MM = (3.0, 16.0)
# The same against the median of the peak's own frequency ring: the maximum of ~10³ Rayleigh
# magnitudes over their median is ≈ 3.5 (measured on noise: ≤ 2.7 for 48²–400² images).
MIN_WHITENED_PEAK_RATIO = 4.5
# Largest ratio of the two directions' periods in one grid.
MAX_PERIOD_RATIO = 1.3
# Second direction must differ from the first by at least this angle (rad); harmonics of the
# first direction lie on its own axis.
MIN_DIRECTION_SEPARATION = np.deg2rad(30.0)


class TagInputError(ValueError):
    """An image that carries no usable tag pattern; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class TagParameters:
    """
    Spacing and orientation of the two tag directions.

    Attributes
    ----------
    spacing_px : ndarray, shape (2,)
        Tag-line spacing per direction, px.
    angles : ndarray, shape (2,)
        Wave-vector angle per direction, rad, in ``[0, π)`` (see module conventions).
    peak_ratio : ndarray, shape (2,)
        Spectral peak magnitude over the annulus median (``inf`` for overrides).
    source : str
        ``"spectrum"``, ``"override"`` or ``"mixed"``.

    """

    spacing_px: np.ndarray
    angles: np.ndarray
    peak_ratio: np.ndarray = field(default_factory=lambda: np.full(2, np.inf))
    source: str = 'override'

    @property
    def wavevectors(self) -> np.ndarray:
        """Return wave vectors ``k_d = 2π/λ_d (sin θ_d, cos θ_d)``, rad/px, (2, 2), (row, col)."""
        a = np.asarray(self.angles, float)
        return (2 * np.pi / np.asarray(self.spacing_px, float))[:, None] * np.stack(
            [np.sin(a), np.cos(a)], -1
        )


def validate_image(image) -> np.ndarray:
    """Return ``image`` as float64 (H, W) or raise :class:`TagInputError` with the reason."""
    try:
        img = np.asarray(image, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TagInputError(f'image is not numeric: {exc}') from None
    if img.ndim != 2:
        raise TagInputError(f'image must be 2-D, got shape {img.shape}')
    if min(img.shape) < 16:
        raise TagInputError(
            f'image too small for tag analysis: {img.shape[0]}x{img.shape[1]} px (need ≥ 16x16)'
        )
    # The extremes say at once whether any pixel is NaN or ±Inf (both propagate into them): the
    # pixels are counted only then. max |img| is the larger of |min| and |max|.
    lo, hi = float(img.min()), float(img.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = int(np.count_nonzero(~np.isfinite(img)))
        raise TagInputError(f'image has {bad} non-finite pixel(s) (NaN/Inf)')
    if hi - lo <= 1e-12 * max(1.0, abs(lo), abs(hi)):
        raise TagInputError('image is constant')
    return img


def _fold_angle(theta):
    return np.mod(theta, np.pi)


def estimate_tag_parameters(
    image,
    mask=None,
    min_spacing_px: float = MIN_SPACING_PX,
    max_spacing_px: float = MAX_SPACING_PX,
    min_peak_ratio: float | None = None,
    whiten: bool = False,
) -> TagParameters:
    """
    Estimate the two tag directions and spacings from the spectrum of an (ED) image.

    The two strongest peaks of the magnitude spectrum (Hann window, or the tapered region when
    ``mask`` is given) inside the annulus ``1/max_spacing ≤ |f| ≤ 1/min_spacing`` that are at least
    30° apart are the two fundamental tag frequencies (any angle, any period in the range); each is
    refined to sub-bin accuracy by a parabola through the log magnitude. A peak is measured against
    the median magnitude of the whole annulus, or with ``whiten`` against the median of its own
    ring ``|f| = const``: anatomy (the wall's, cavity's and body's edges) falls off steeply with
    ``|f|``, so unwhitened a strong edge at low frequency can outrank faint tags, while whitened a
    thin tagged wall (whose tag peak is spread over much of its ring) can sink below its ring.
    Neither is right for every image; :func:`mlv_ros.core.tags.estimate_grid` tries both and lets
    the image's Gabor responses decide.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Tagged image (best at end-diastole, where the grid is undeformed).
    mask : array_like of bool, shape (H, W), optional
        Region whose spectrum is analysed (e.g. myocardium dilated); default the whole image.
    min_spacing_px, max_spacing_px : float
        Search range for the spacing, px.
    min_peak_ratio : float, optional
        Each peak must exceed this multiple of its reference median (scale-free: the image's own
        spectrum is the reference). Default :data:`MIN_PEAK_RATIO`, or
        :data:`MIN_WHITENED_PEAK_RATIO` with ``whiten``.
    whiten : bool
        Measure each frequency against its own ring (see above).

    Returns
    -------
    TagParameters
        ``peak_ratio`` holds each direction's peak height over its reference median.

    Raises
    ------
    TagInputError
        Invalid image, or no pair of tag peaks (no tags, tags faded, pure noise).

    """
    img = validate_image(image)
    h, w = img.shape
    if min_peak_ratio is None:
        min_peak_ratio = MIN_WHITENED_PEAK_RATIO if whiten else MIN_PEAK_RATIO
    work = _spectral_input(img, mask, min_spacing_px, max_spacing_px)
    spec = np.abs(sfft.fft2(work))
    if not whiten:
        # Power averaged over neighbouring bins (σ = 1 bin): a tag peak is at least that wide (the
        # window's or the region's own spectrum) while noise averages down. (Whitened, the ring
        # median would rise with a spread peak instead.)
        spec = np.sqrt(ndi.gaussian_filter(spec**2, 1.0, mode='wrap'))
    fr, fc, rad, ang, half = _frequency_grid(h, w)
    # Half plane (fc > 0, or fc == 0 and fr > 0): the spectrum of a real image is Hermitian.
    annulus = half & (rad >= 1.0 / max_spacing_px) & (rad <= 1.0 / min_spacing_px)
    if not annulus.any():
        raise TagInputError(
            f'image {h}x{w} too small to resolve tag spacings up to {max_spacing_px} px'
        )
    # The search runs over the annulus' frequencies only (≈ 1/6 of the spectrum), in row-major
    # order, so the first maximum is the one a whole-spectrum argmax finds.
    band = np.flatnonzero(annulus)
    spec_a, rad_a, ang_a = spec.ravel()[band], rad.ravel()[band], ang.ravel()[band]
    score = _peak_scores(spec_a, rad_a, (h, w), whiten)
    peaks = []
    for _ in range(2):
        best = int(np.argmax(score))
        idx = np.unravel_index(int(band[best]), spec.shape)
        ratio = float(score[best])
        if ratio < min_peak_ratio:
            which = 'first' if not peaks else 'second'
            ref = "its ring's" if whiten else "the band's"
            raise TagInputError(
                f'no {which} tag direction: strongest spectral peak is {ratio:.1f}x {ref} '
                f'median (need ≥ {min_peak_ratio:g}); no tags, faded tags or noise only'
            )
        f = np.array([_subbin(spec, idx, 0) / h, _subbin(spec, idx, 1) / w])
        f = np.array([(f[0] + 0.5) % 1.0 - 0.5, (f[1] + 0.5) % 1.0 - 0.5])  # back to [-0.5, 0.5)
        if mask is not None:
            f = _refine_peak(work, f)
        peaks.append((f, ratio))
        score = _suppressed(score, f, rad_a, ang_a)
    spacing = np.array([1.0 / np.hypot(*p[0]) for p in peaks])
    angles = _fold_angle(np.array([np.arctan2(p[0][0], p[0][1]) for p in peaks]))
    order = np.argsort(angles)
    return TagParameters(
        spacing_px=spacing[order],
        angles=angles[order],
        peak_ratio=np.array([p[1] for p in peaks])[order],
        source='spectrum',
    )


def _spectral_input(img, mask, min_spacing_px, max_spacing_px):
    """Return the image made ready for its spectrum: tapered region or Hann-windowed frame."""
    h, w = img.shape
    if mask is None:
        return (img - img.mean()) * np.outer(np.hanning(h), np.hanning(w))
    m = np.asarray(mask, bool)
    if m.shape != img.shape:
        raise TagInputError(f'mask shape {m.shape} differs from image shape {img.shape}')
    if m.sum() < 16:
        raise TagInputError('mask has fewer than 16 pixels')
    # Remove the local mean (the region's own shape would otherwise dominate the low
    # frequencies) and taper the region's edge so it does not ring into the tag band.
    sig = 0.5 * max_spacing_px
    mf = m.astype(np.float32)
    den = np.maximum(cv2.GaussianBlur(mf, (0, 0), sig), 1e-3)
    local = cv2.GaussianBlur((img * mf).astype(np.float32), (0, 0), sig) / den
    taper = cv2.GaussianBlur(mf, (0, 0), 0.25 * min_spacing_px + 1.0)
    return (img - local) * taper


def _peak_scores(spec_a, rad_a, shape, whiten):
    """Score each band frequency against the band's median, or whitened its ring's."""
    if whiten:
        # Rings one frequency bin wide (of the longer side); each frequency over its ring's median
        # (as ndimage.median over the ring labels: sorted by ring, then value).
        ring = np.rint(rad_a * max(shape)).astype(np.int64)
        order = np.lexsort((spec_a, ring))
        sorted_spec = spec_a[order]
        ids, start, count = np.unique(ring[order], return_index=True, return_counts=True)
        med = (sorted_spec[start + (count - 1) // 2] + sorted_spec[start + count // 2]) / 2
        if not np.all(med > 0):
            raise TagInputError('image spectrum is empty in the tag frequency band')
        return spec_a / med[np.searchsorted(ids, ring)]
    med = float(np.median(spec_a))
    if med <= 0:
        raise TagInputError('image spectrum is empty in the tag frequency band')
    return spec_a / med


def _suppressed(score, f, rad_a, ang_a):
    """
    Zero the scores a second tag direction cannot have, given the first peak ``f`` (cycles/px).

    Everything within 30° of this direction (its harmonics too), and periods far from this one:
    a SPAMM grid's two directions share (nearly) one period, while a second peak at another
    period is anatomy (e.g. a thin wall's own edges).
    """
    theta = np.arctan2(f[0], f[1])
    diff = np.abs(np.angle(np.exp(1j * 2 * (ang_a - theta)))) / 2  # axial distance, [0, π/2]
    f_abs = np.hypot(*f)
    return np.where(
        (diff < MIN_DIRECTION_SEPARATION)
        | (rad_a < f_abs / MAX_PERIOD_RATIO)
        | (rad_a > f_abs * MAX_PERIOD_RATIO),
        0.0,
        score,
    )


@lru_cache(maxsize=16)
def _frequency_grid(h: int, w: int):
    """
    Return the FFT frequency grid of an (h, w) image, read-only, cycles / px.

    ``(fr (h, 1), fc (1, w), |f| (h, w), angle atan2(fr, fc) (h, w) in rad, half-plane mask
    (h, w): fc > 0, or fc == 0 and fr > 0)``.
    """
    fr = sfft.fftfreq(h)[:, None]
    fc = sfft.fftfreq(w)[None, :]
    out = (fr, fc, np.hypot(fr, fc), np.arctan2(fr, fc), (fc > 0) | ((fc == 0) & (fr > 0)))
    for a in out:
        a.setflags(write=False)
    return out


def _refine_peak(work: np.ndarray, f: np.ndarray, steps: int = 9) -> np.ndarray:
    """
    Return the frequency (cycles/px, (row, col)) maximising ``|Σ work(x) e^{−2πi f·x}|``.

    The search is within ±1 bin of ``f``.

    A thin tagged region spreads its tag peak over many bins and the parabola through three of
    them is then biased by the neighbouring copies; the region's own transform still peaks at the
    tag frequency, so the DFT evaluated off the bin lattice finds it (separable: two small matrix
    products per candidate row).
    """
    h, w = work.shape
    rows, cols = np.arange(h), np.arange(w)
    best, best_f = -1.0, f
    for _ in range(2):  # coarse ±1 bin, then ±1/4 bin around the best
        span = 1.0 if best < 0 else 0.25
        fr = best_f[0] + np.linspace(-span, span, steps) / h
        fc = best_f[1] + np.linspace(-span, span, steps) / w
        er = np.exp(-2j * np.pi * np.outer(fr, rows))  # (steps, h)
        ec = np.exp(-2j * np.pi * np.outer(cols, fc))  # (w, steps)
        mag = np.abs(er @ work @ ec)  # (steps, steps)
        i, j = np.unravel_index(int(np.argmax(mag)), mag.shape)
        best, best_f = float(mag[i, j]), np.array([fr[i], fc[j]])
    return best_f


def _subbin(spec, idx, axis):
    """Sub-bin index of a spectral peak along ``axis`` (parabola through log magnitudes)."""
    n = spec.shape[axis]
    i = idx[axis]
    lo = list(idx)
    hi = list(idx)
    lo[axis] = (i - 1) % n
    hi[axis] = (i + 1) % n
    a, b, c = (
        np.log(spec[tuple(lo)] + 1e-30),
        np.log(spec[idx] + 1e-30),
        np.log(spec[tuple(hi)] + 1e-30),
    )
    den = a - 2 * b + c
    off = 0.5 * (a - c) / den if den < 0 else 0.0
    # fftfreq index → signed index
    si = i if i < (n + 1) // 2 else i - n
    return si + float(np.clip(off, -0.5, 0.5))


def resolve_parameters(
    image, mask=None, spacing_px=None, angles=None, estimate=None
) -> TagParameters:
    """
    Tag parameters from overrides, completing missing ones from the spectrum.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Tagged image.
    mask : array_like of bool, optional
        Region for :func:`estimate_tag_parameters` when something must be estimated (the whole
        image is tried if the region alone gives no peaks).
    spacing_px : float or array_like of 2 floats, optional
        Tag spacing, px (one value for both directions, or one per direction).
    angles : array_like of 2 floats, optional
        Wave-vector angles, rad (module conventions).
    estimate : callable, optional
        ``estimate(image, mask) -> TagParameters`` (default :func:`estimate_tag_parameters`).

    Returns
    -------
    TagParameters

    """
    estimate = estimate or estimate_tag_parameters
    if spacing_px is not None and angles is not None:
        sp = np.broadcast_to(np.asarray(spacing_px, float), (2,)).copy()
        an = _fold_angle(np.asarray(angles, float).reshape(2))
        if not (np.all(np.isfinite(sp)) and np.all(sp >= 2.0)):
            raise TagInputError(f'tag spacing override must be finite and ≥ 2 px, got {sp}')
        if not np.all(np.isfinite(an)):
            raise TagInputError(f'tag angle override must be finite, got {an}')
        return TagParameters(spacing_px=sp, angles=an, source='override')
    try:
        est = estimate(image, mask)
    except TagInputError:
        if mask is None:
            raise
        est = estimate(image, None)  # small or odd regions: the whole image's grid
    if spacing_px is None and angles is None:
        return est
    sp = (
        est.spacing_px
        if spacing_px is None
        else np.broadcast_to(np.asarray(spacing_px, float), (2,)).copy()
    )
    an = est.angles if angles is None else _fold_angle(np.asarray(angles, float).reshape(2))
    if angles is not None and spacing_px is None:
        # Pair each overridden angle with the estimated spacing of the nearest estimated direction.
        d = np.abs(np.angle(np.exp(2j * (an[:, None] - est.angles[None, :]))))
        sp = est.spacing_px[np.argmin(d, axis=1)]
    return TagParameters(spacing_px=sp, angles=an, peak_ratio=est.peak_ratio, source='mixed')


@lru_cache(maxsize=64)
def _kernel_bank_cached(shape, spacings, angles, sigma_u, sigma_v):
    h, w = shape
    fr = sfft.fftfreq(h)[:, None]
    fc = sfft.fftfreq(w)[None, :]
    out = np.empty((len(spacings), h, w), np.complex64)
    for j, (lam, th) in enumerate(zip(spacings, angles)):
        ur, uc = np.sin(th), np.cos(th)  # unit wave vector (row, col)
        su, sv = sigma_u * lam, sigma_v * lam  # spatial envelope std along / across the wave, px
        fu = fr * ur + fc * uc  # frequency component along the wave, cycles/px
        fv = -fr * uc + fc * ur
        f0 = 1.0 / lam

        def env(a, b):
            return np.exp(-2 * np.pi**2 * (su**2 * a**2 + sv**2 * b**2))

        # Continuous-domain transform of g(x)(exp(i2πf0·x) − c) with c = exp(−2π²σu²f0²):
        # the subtracted term removes the kernel mean (zero response to DC / smooth anatomy).
        out[j] = env(fu - f0, fv) - np.exp(-2 * np.pi**2 * su**2 * f0**2) * env(fu, fv)
    out.setflags(write=False)
    return out


def kernel_bank(
    shape,
    params: TagParameters,
    direction: int,
    orientations_deg=(-12.0, 0.0, 12.0),
    spacing_factors=(0.8, 1.0, 1.25),
    sigma_u: float = 0.5,
    sigma_v: float = 0.6,
) -> np.ndarray:
    """
    Frequency responses of the Gabor kernels of one tag direction.

    Each kernel is ``g(x) (exp(i 2π x_u/λ) − c)`` with a Gaussian envelope ``g`` of standard
    deviations ``sigma_u·λ`` along the wave vector and ``sigma_v·λ`` along the tag lines and ``c``
    making its mean zero; its transform peaks at 1 at the tuned frequency, so a cosine of
    amplitude ``A`` at that frequency gives ``|R| = A/2``.

    Parameters
    ----------
    shape : tuple of int
        Image shape (H, W).
    params : TagParameters
        Tag spacing and wave-vector angle of each direction.
    direction : int
        0 or 1.
    orientations_deg : sequence of float
        Offsets of the wave-vector angle around ``params.angles[direction]``, degrees.
    spacing_factors : sequence of float
        Multipliers of ``params.spacing_px[direction]``.
    sigma_u, sigma_v : float
        Envelope standard deviations in units of the kernel's spacing.

    Returns
    -------
    ndarray of complex64, shape (n_orientations·n_spacings, H, W)
        Read-only, FFT-ordered (``scipy.fft.fftfreq``) frequency responses.

    """
    return _kernel_bank_cached(
        tuple(int(v) for v in shape),
        *_bank_tuning(
            float(params.spacing_px[direction]),
            float(params.angles[direction]),
            tuple(float(o) for o in orientations_deg),
            tuple(float(f) for f in spacing_factors),
        ),
        float(sigma_u),
        float(sigma_v),
    )


@lru_cache(maxsize=256)
def _bank_tuning(lam0: float, th0: float, orientations_deg: tuple, spacing_factors: tuple):
    """
    Return the bank's kernel spacings (px) and wave-vector angles (rad), rounded for the cache.

    Orientation-major, each a tuple (the key of ``_kernel_bank_cached``); remembered, since
    every frame of a slice asks for the same bank.
    """
    sp, an = [], []
    for o in orientations_deg:
        for s in spacing_factors:
            sp.append(round(lam0 * s, 6))
            an.append(round(th0 + np.deg2rad(o), 6))
    return tuple(sp), tuple(an)


@dataclass
class GaborMaps:
    """
    Best Gabor response per pixel and direction.

    Attributes
    ----------
    response : ndarray of complex64, shape (2, H, W)
        Complex response of the kernel with the largest magnitude at each pixel; phase ≡ π on
        dark tag centres.
    magnitude : ndarray of float32, shape (2, H, W)
        ``|response|``, image intensity units (a cosine of amplitude A gives A/2).
    kernel_index : ndarray of int8, shape (2, H, W)
        Index of the winning kernel (orientation-major, see :func:`kernel_bank`).

    """

    response: np.ndarray
    magnitude: np.ndarray
    kernel_index: np.ndarray

    @property
    def phase(self) -> np.ndarray:
        """Return the wrapped phase in (−π, π], rad, shape (2, H, W)."""
        return np.angle(self.response)


def gabor_filter_bank(
    image,
    params: TagParameters,
    orientations_deg=(-12.0, 0.0, 12.0),
    spacing_factors=(0.8, 1.0, 1.25),
    sigma_u: float = 0.5,
    sigma_v: float = 0.6,
) -> GaborMaps:
    """
    Filter an image with the Gabor bank of both tag directions (FFT, one batch per direction).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Finite pixels (see :func:`validate_image`).
    params : TagParameters
        Tag spacing and wave-vector angle of each direction (the bank's centre).
    orientations_deg, spacing_factors, sigma_u, sigma_v
        See :func:`kernel_bank`. The defaults span ±12° of rotation and −20 %…+25 % of spacing
        change, the range of in-plane tag deformation over a cardiac cycle.

    Returns
    -------
    GaborMaps

    """
    img = np.asarray(image, np.float32)
    h, w = img.shape
    # Zero-pad (after removing the mean) to a fast FFT size on a 32-px lattice, so that crops of
    # slightly different sizes share cached kernel banks.
    fh, fw = (sfft.next_fast_len(-(-n // 32) * 32) for n in (h, w))
    spec = sfft.fft2(img - img.mean(), s=(fh, fw)).astype(np.complex64, copy=False)
    resp = np.empty((2, h, w), np.complex64)
    mag = np.empty((2, h, w), np.float32)
    kidx = np.empty((2, h, w), np.int8)
    for d in range(2):
        bank = kernel_bank(
            (fh, fw), params, d, orientations_deg, spacing_factors, sigma_u, sigma_v
        )
        # The inverse FFTs in place on the products, the winners gathered along the kernel axis
        # by flat indices (the same values as np.take_along_axis, a third of its time)
        full = sfft.ifft2(bank * spec, axes=(-2, -1), workers=1, overwrite_x=True)
        a = np.abs(full[:, :h, :w])
        k = np.argmax(a, axis=0)
        at_full, at_window = _pixel_offsets(h, w, fw)
        resp[d] = full.ravel().take(k * (fh * fw) + at_full)
        mag[d] = a.ravel().take(k * (h * w) + at_window)
        kidx[d] = k
    return GaborMaps(response=resp, magnitude=mag, kernel_index=kidx)


@lru_cache(maxsize=64)
def _pixel_offsets(h: int, w: int, fw: int):
    """
    Return the flat offsets of an (h, w) window's pixels in a row of ``fw`` and in its own rows.

    Both (h, w) ``intp``, read-only: pixel (r, c) of plane k of a C-ordered (K, fh, fw) array is
    at ``k·fh·fw + r·fw + c``, of a (K, h, w) array at ``k·h·w + r·w + c``.
    """
    rows, cols = np.arange(h)[:, None], np.arange(w)[None, :]
    out = ((rows * fw + cols).astype(np.intp), (rows * w + cols).astype(np.intp))
    for a in out:
        a.setflags(write=False)
    return out

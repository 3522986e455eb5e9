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
Tag intersections from Gabor phase maps.

Candidates, sub-pixel Newton refinement, confidence, myocardium restriction and grid labels.

A tag line of direction ``d`` is where the Gabor phase is ≡ π (dark tags; see
:mod:`mlv_ros.core.tags.gabor`), so with ``ψ_d = wrap(φ_d − π)`` an intersection is a common root
of ``ψ_1`` and ``ψ_2``. Every pixel predicts the root nearest to it by one Newton step on the
linearised phases; a pixel is a candidate when that root falls inside its own pixel cell, which
gives one candidate per intersection without thresholds on the phase.

References
----------
Chen, T. et al. IEEE TMI 29(1):1–11, 2010 (Gabor phase maps, tag intersections).

"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
from mlv_ros.core.filters import running_median
import numpy as np
from scipy.spatial import cKDTree

from .gabor import (
    estimate_tag_parameters,
    gabor_filter_bank,
    GaborMaps,
    MAX_SPACING_PX,
    MIN_SPACING_PX,
    resolve_parameters,
    TagInputError,
    TagParameters,
    validate_image,
)
from .phase import PhaseField, solve_phase

# |R_d| / σ_local for an ideal 1-1 SPAMM grid: each direction is a cosine of amplitude 1/4
# (|R| = 1/8) and the grid's variance is 5/64, so the ratio is (1/8)/sqrt(5/64) = 1/sqrt(5).
IDEAL_CONTRAST_RATIO = 1.0 / np.sqrt(5.0)
# Coverage normalisation (detect_intersections(coverage_normalised=True)) divides by at most
# 1/sqrt(COVERAGE_FLOOR): beyond that a point sees more outside the mask than inside it.
COVERAGE_FLOOR = 0.25
DEFAULT_MIN_CONFIDENCE = 0.4  # detect_intersections' threshold (confidence 0..1)
# A region's tag grid must explain at least this much of its contrast coherently
# (:func:`grid_coherence`; an ideal grid gives IDEAL_CONTRAST_RATIO ≈ 0.45, tagged ED walls at
# SNR 12 measured 0.40–0.43 in their true outline, untagged anatomy and noise ≤ 0.11). Below it
# the region is not taken as tagged wall and the whole image's grid is used instead.
MIN_GRID_COHERENCE = 0.15
# Spectral peak heights that make a candidate when a region's coherence has the last word
# (noise alone reaches ≈ 2.7 band / 4.3 whitened: some noise candidates are expected and rejected).
PERMISSIVE_PEAK_RATIO = 3.0
PERMISSIVE_WHITENED_PEAK_RATIO = 2.5
# Default largest move of the tuned refinement (:func:`refine_tuned`), px: beyond it the bank's and
# the tuned kernels disagree (clutter, wrong tuning) and the point is dropped. Followers of known
# tracks pass their own limit in tag periods (``max_tuned_move_periods``).
TUNED_MAX_MOVE_PX = 0.5


@dataclass
class Detection:
    """
    Tag intersections found in one image.

    Attributes
    ----------
    pixel_rc : ndarray, shape (N, 2)
        Sub-pixel (row, col), px.
    labels : ndarray of int32, shape (N, 2)
        Grid indices (k1, k2): tag-line number per direction counted from the line nearest the
        image centre, from the phase against the straight ED grid (reliable while the grid is
        deformed by less than half a spacing relative to straight lines, i.e. at ED).
    confidence : ndarray of float32, shape (N,)
        0..1: geometric mean over the two directions of ``|R_d| / (σ_local/√5)`` clipped to 1,
        where ``σ_local`` is the local intensity standard deviation (1 for an ideal noise-free
        grid).
    residual : ndarray of float32, shape (N,)
        Phase residual after refinement, rad.
    plain_confidence : ndarray of float32, shape (N,)
        ``confidence`` before the coverage normalisation (equal to it when not normalised).
    params : TagParameters or None
        Tag parameters used (None when the image was rejected before they were known).
    reason : str
        Empty on success; otherwise why there are no points (the result is then empty).
    maps : GaborMaps or None
        Filter-bank output, only when requested with ``keep_maps=True``.

    """

    pixel_rc: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    labels: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    residual: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    plain_confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    params: TagParameters | None = None
    reason: str = ''
    maps: GaborMaps | None = None

    def __len__(self) -> int:
        return int(self.pixel_rc.shape[0])

    @property
    def ok(self) -> bool:
        return not self.reason


def local_std(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted local standard deviation, same units as ``image``, shape (H, W)."""
    img = np.asarray(image, np.float32)
    m = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    m2 = cv2.GaussianBlur(img * img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(m2 - m * m, 0.0))


def masked_normalise(image: np.ndarray, mask: np.ndarray, sigma: float):
    """
    Zero-mean the image locally inside a mask and zero it outside (normalised convolution).

    The untagged blood pool next to the myocardium is a strong intensity step that leaks into the
    Gabor phase (up to ≈ 1 px bias at the endocardium); removing the masked local mean and the
    outside leaves only the (truncated) tag pattern.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Image to normalise.
    mask : ndarray of bool, shape (H, W)
        Region kept (e.g. the myocardium); zero outside.
    sigma : float
        Gaussian window standard deviation, px.

    Returns
    -------
    work : ndarray of float32, shape (H, W)
        ``mask·(I − G*(mI)/G*(m))``.
    std : ndarray of float32, shape (H, W)
        Masked local standard deviation ``sqrt(G*(m·work²)/G*(m))``.

    """
    img = np.asarray(image, np.float32)
    m = mask.astype(np.float32)
    den = np.maximum(cv2.GaussianBlur(m, (0, 0), sigma, borderType=cv2.BORDER_REFLECT), 1e-3)
    mean = cv2.GaussianBlur(img * m, (0, 0), sigma, borderType=cv2.BORDER_REFLECT) / den
    work = m * (img - mean)
    var = cv2.GaussianBlur(work * work, (0, 0), sigma, borderType=cv2.BORDER_REFLECT) / den
    return work, np.sqrt(np.maximum(var, 0.0))


def confidence_map(
    image: np.ndarray, maps: GaborMaps, params: TagParameters, std=None
) -> np.ndarray:
    """
    Return the per-pixel tag confidence in 0..1, shape (H, W) (see :class:`Detection`).

    ``std`` is the local standard deviation if already known.
    """
    sig = local_std(image, float(np.mean(params.spacing_px))) if std is None else std
    floor = 1e-6 * float(np.ptp(image)) + 1e-30
    r = maps.magnitude / (IDEAL_CONTRAST_RATIO * np.maximum(sig, floor))[None]
    return np.sqrt(np.clip(r[0], 0, 1) * np.clip(r[1], 0, 1)).astype(np.float32)


def _same_grid(a: TagParameters, b: TagParameters) -> bool:
    """Both directions within 2° and 3 % of spacing (in either order)."""
    for perm in ((0, 1), (1, 0)):
        da = np.abs(np.angle(np.exp(2j * (a.angles - b.angles[list(perm)])))) / 2
        ds = np.abs(a.spacing_px / b.spacing_px[list(perm)] - 1)
        if np.all(da < np.deg2rad(2.0)) and np.all(ds < 0.03):
            return True
    return False


def grid_coherence(
    image, params: TagParameters, region=None, smoothing_px: float | None = None
) -> float:
    """
    How well one undeformed tag grid explains an image, in 0..1 (scale-free).

    At end-diastole the grid is a plane wave per direction over all tagged tissue, so its
    demodulated responses add up coherently: ``|Σ w(x) e^{−i k_d·x}|`` (``w`` the region's
    locally zero-meaned image, :func:`masked_normalise`) is largest at the true wave vectors, and
    noise, anatomy edges or a wrong grid add up incoherently. The score is the geometric mean over
    the two directions, over ``sqrt(Σ w² · area)`` (1 for a region holding nothing but one cosine).

    Parameters
    ----------
    image : ndarray, shape (H, W)
        Tagged image.
    params : TagParameters
        The grid scored: tag spacing and wave-vector angle of each direction.
    region : ndarray of bool, shape (H, W), optional
        Where tags are expected (the myocardium); default the whole image.
    smoothing_px : float, optional
        Local-mean window σ, px (default the grid's mean spacing). Scores of several grids are
        comparable only with one common value.

    Returns
    -------
    float

    """
    work, origin, norm = _coherence_input(
        image, region, smoothing_px or float(np.mean(params.spacing_px))
    )
    return _coherence(work, origin, params.wavevectors) / norm


def _coherence_input(image, region, smoothing_px: float):
    """
    Return what :func:`grid_coherence` scores every grid on: ``(work, origin, normaliser)``.

    ``work`` the region's locally zero-meaned image cropped to its bounding box (the whole image
    less its mean without a region), ``origin`` the box's first (row, col), px, and the
    normaliser ``sqrt(Σ work² · area)``. The same for every candidate grid of one image, region
    and ``smoothing_px`` (:func:`estimate_grid` computes it once).
    """
    img = np.asarray(image, np.float64)
    if region is not None and np.any(region):
        rows, cols = np.nonzero(region)
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        reg = np.asarray(region, bool)
        work, _ = masked_normalise(img, reg, smoothing_px)
        work, n = work[r0:r1, c0:c1].astype(np.float64), float(reg.sum())
    else:
        r0 = c0 = 0
        work, n = img - img.mean(), float(img.size)
    return work, (r0, c0), max(np.sqrt(float(np.sum(work**2)) * n), 1e-300)


def _coherence(work, origin, wavevectors) -> float:
    """Geometric mean over directions of ``|Σ work(x) e^{−i k·x}|`` (separable, (row, col) px)."""
    rows = origin[0] + np.arange(work.shape[0])
    cols = origin[1] + np.arange(work.shape[1])
    out = 1.0
    for k in np.asarray(wavevectors, float):
        out *= abs(np.exp(-1j * k[0] * rows) @ work @ np.exp(-1j * k[1] * cols))
    return float(np.sqrt(out))


def _half_sum_difference(p: TagParameters) -> TagParameters:
    """
    Return the grid whose cross terms k1 ± k2 are ``p``'s two wave vectors.

    Half their sum and difference (a grid's cross terms are spectral peaks too, at 45° and 1/√2 of
    its period).
    """
    k = p.wavevectors / (2 * np.pi)
    derived = [(k[0] + k[1]) / 2, (k[0] - k[1]) / 2]
    return TagParameters(
        spacing_px=np.array([1.0 / np.hypot(*d) for d in derived]),
        angles=np.mod([np.arctan2(d[0], d[1]) for d in derived], np.pi),
        peak_ratio=p.peak_ratio,
        source='spectrum',
    )


def _related_grids(p: TagParameters) -> list[TagParameters]:
    """
    Return ``p``, the grid of which it holds the cross terms, and related orthogonal grids.

    The orthogonal equal-period grids of each of their directions (and theirs): on a thin wall
    often one direction is found well and the other is noise, or a cross term outranks a
    fundamental.
    """
    out = [p, _half_sum_difference(p)]
    for g in out[:2]:
        for d in (0, 1):
            o = TagParameters(
                spacing_px=np.full(2, g.spacing_px[d]),
                angles=np.mod(g.angles[d] + np.array([0.0, np.pi / 2]), np.pi),
                peak_ratio=p.peak_ratio,
                source='spectrum',
            )
            out += [o, _half_sum_difference(o)]
    return out


def estimate_grid(
    image,
    mask=None,
    score_region=None,
    spacing_range_px: tuple[float, float] = (MIN_SPACING_PX, MAX_SPACING_PX),
) -> TagParameters:
    """
    Tag spacing and directions of one image, chosen by the image's own Gabor responses.

    Candidates come from the spectrum of the region (``mask``), of the whole image and of the
    whole image less its running median (a bright region's outline removed), each
    measured against the tag band's median and against its own frequency ring
    (:func:`~mlv_ros.core.tags.gabor.estimate_tag_parameters` with and without ``whiten``): on a
    thin tagged wall the tag peak is spread over its ring, on a high-contrast background the
    anatomy's edges dominate low frequencies, and a thin region's own shape can outrank its tags.
    Each candidate is also completed to the orthogonal equal-period grid of either of its
    directions (the usual SPAMM grid; on a thin wall one direction is often found well and the
    other not). The candidate with the highest :func:`grid_coherence` over ``score_region`` wins.

    Parameters
    ----------
    image : array_like, shape (H, W)
        Tagged image.
    mask : array_like of bool, shape (H, W), optional
        Region for the regional spectrum (e.g. the myocardium dilated).
    score_region : array_like of bool, shape (H, W), optional
        Where candidates are scored (e.g. the myocardium); default ``mask``, else the whole image.
    spacing_range_px : (float, float)
        Tag periods considered, px (e.g. the physical range of SPAMM grids over the pixel size).

    Returns
    -------
    TagParameters

    Raises
    ------
    TagInputError
        No spectrum gives a pair of tag peaks (the first reason is given).

    """
    img = validate_image(image)
    region = score_region if score_region is not None else mask
    # With a region, faint peaks are candidates too: the coherence test below tells tags from
    # anatomy and noise far better than any spectral peak height (measured: ED tagged walls
    # 0.40–0.43, untagged anatomy ≤ 0.11). Without one, the spectrum's own tests decide.
    thresholds = (
        {False: PERMISSIVE_PEAK_RATIO, True: PERMISSIVE_WHITENED_PEAK_RATIO}
        if region is not None
        else {}
    )
    cands: list[TagParameters] = []
    reasons = []
    # Also the image less its running median over the longest period: the median follows a
    # uniform region brighter than the tagged wall (a bright blood pool, an LA cavity with its
    # flat basal cut) edge and all, so its outline, whose spectrum falls off as 1/frequency and
    # out-weighed a thin wall's tags in LA views (15 mm "grids" found for 9 mm tags), leaves the
    # tag band, while the tags, finer than the window, stay (as segment.tag_wavevectors does).
    # Only where a region can score the extra candidates.
    sources = [(img, mask)] if mask is not None else []
    sources.append((img, None))
    if region is not None:
        size = int(np.ceil(spacing_range_px[1])) | 1
        sources.append((img - running_median(img, size), None))
    for source, spec_region in sources:
        for whiten in (False, True):
            try:
                p = estimate_tag_parameters(
                    source,
                    spec_region,
                    *spacing_range_px,
                    min_peak_ratio=thresholds.get(whiten),
                    whiten=whiten,
                )
            except TagInputError as exc:
                reasons.append(str(exc))
                continue
            for c in _related_grids(p):
                if (
                    np.all(c.spacing_px >= spacing_range_px[0])
                    and np.all(c.spacing_px <= spacing_range_px[1])
                    and not any(_same_grid(c, o) for o in cands)
                ):
                    cands.append(c)
    if not cands:
        raise TagInputError(reasons[0])
    if len(cands) == 1 and region is None:
        return cands[0]
    # One local-mean window for all (the score's normalisation depends on it).
    smooth = float(np.median([np.mean(c.spacing_px) for c in cands]))
    work, origin, norm = _coherence_input(img, region, smooth)  # grid_coherence's, once
    scores = [_coherence(work, origin, p.wavevectors) / norm for p in cands]
    best = int(np.argmax(scores))
    if region is not None and scores[best] < MIN_GRID_COHERENCE:
        raise TagInputError(
            f'no tag grid in the region: the best of {len(cands)} candidate grids explains '
            f'{scores[best]:.2f} of its contrast coherently (need ≥ {MIN_GRID_COHERENCE:g}; '
            f'an ideal grid gives {IDEAL_CONTRAST_RATIO:.2f})'
        )
    return cands[best]


def grid_labels(pixel_rc: np.ndarray, params: TagParameters, shape, weights=None) -> np.ndarray:
    """
    Grid indices (k1, k2) of intersections of an (almost) undeformed grid.

    The straight-grid phase ``k_d·(x − centre)`` plus one global offset per direction (circular
    weighted mean over the points) is ≡ 0 mod 2π at the intersections; the integer number of
    turns is the label.

    Parameters
    ----------
    pixel_rc : ndarray, shape (N, 2)
        Intersection positions, (row, col) px.
    params : TagParameters
        Tag spacing and wave-vector angle of each direction of the grid.
    shape : tuple
        Image shape (H, W); labels count from the centre pixel.
    weights : ndarray, shape (N,), optional
        Weights of the points in the circular mean of each direction's offset (default all 1).

    Returns
    -------
    ndarray of int32, shape (N, 2)

    """
    if len(pixel_rc) == 0:
        return np.zeros((0, 2), np.int32)
    centre = (np.asarray(shape, float) - 1) / 2
    lin = (np.asarray(pixel_rc, float) - centre) @ params.wavevectors.T  # (N, 2) rad
    w = np.ones(len(lin)) if weights is None else np.asarray(weights, float)
    off = -np.angle(np.sum(w[:, None] * np.exp(1j * lin), axis=0))
    return np.rint((lin + off) / (2 * np.pi)).astype(np.int32)


def refine_tuned(
    image: np.ndarray,
    points: np.ndarray,
    wavevectors: np.ndarray,
    sigma_u: float = 0.5,
    sigma_v: float = 0.6,
    iterations: int = 2,
):
    """
    Re-locate intersections with Gabor kernels tuned to each point's local wave vectors.

    The filter bank quantises orientation and spacing; next to the myocardium border (where the
    signal is truncated) a kernel detuned by ~7° / 7 % biases the phase by up to ~0.3 px, while a
    tuned kernel does not (measured on analytic annuli). So at each point the two responses are
    recomputed by direct summation over a patch with kernels tuned to the local phase gradient,
    and Newton's method (Jacobian = the two wave vectors) is iterated on their phases.

    Parameters
    ----------
    image : ndarray, shape (H, W)
        The filtered image (already mean-removed/masked as for the bank).
    points : ndarray, shape (N, 2)
        First-pass positions, (row, col) px.
    wavevectors : ndarray, shape (N, 2, 2)
        ``wavevectors[n, d]`` = ∇ψ_d at the point, rad/px (row, col).
    sigma_u, sigma_v : float
        Envelope standard deviations in units of the local spacing (as in the bank).
    iterations : int
        Newton steps (at least 1).

    Returns
    -------
    x : ndarray, shape (N, 2)
        Refined positions.
    magnitude : ndarray, shape (N, 2)
        Tuned response magnitudes.
    ok : ndarray of bool, shape (N,)
        False where the local wave vectors are degenerate.

    """
    img = np.asarray(image, np.float64)
    h, w = img.shape
    x = np.array(points, float).reshape(-1, 2)
    k = np.array(wavevectors, float).reshape(-1, 2, 2)
    ok = _sane_wavevectors(k)
    mag = np.zeros((len(x), 2))
    if not ok.any():
        return x, mag, ok
    if len(x) > 128:  # bound the (N, 2, P) work arrays
        parts = [
            refine_tuned(image, x[i:i + 128], k[i:i + 128], sigma_u, sigma_v, iterations)
            for i in range(0, len(x), 128)
        ]
        return tuple(np.concatenate(z) for z in zip(*parts))
    k0 = k.copy()
    # Patch: 2.5 envelope widths (weight ≥ 0.04 of the peak) of the typical (median) local
    # spacing, +10 % for stretch; a longer kernel is truncated there (its mean is still removed
    # exactly, see c below).
    lam_typ = min(float(np.median(2 * np.pi / np.linalg.norm(k[ok], axis=2))) * 1.1, 32.0)
    half = int(np.ceil(2.5 * max(sigma_u, sigma_v) * lam_typ))
    n = 2 * half + 1
    o = np.arange(-half, half + 1, dtype=np.float32)  # patch offsets, px (rows and columns)
    # Patches are views of the image zero-padded by a whole patch (with a 1/0 twin saying which
    # pixels are inside): a patch centred up to `half` beyond the border sees only padding.
    pad_img = np.zeros((h + 2 * n, w + 2 * n), np.float32)
    pad_img[n:n + h, n:n + w] = img
    pad_in = np.zeros_like(pad_img)
    pad_in[n:n + h, n:n + w] = 1.0
    win_img = np.lib.stride_tricks.sliding_window_view(pad_img, (n, n))
    win_in = np.lib.stride_tricks.sliding_window_view(pad_in, (n, n))
    for _ in range(max(1, iterations)):
        r, dr, gsum = _tuned_response(
            (win_img, win_in), (h, w), (o, half), x, k, (sigma_u, sigma_v)
        )
        # Local wave vector measured by the tuned kernel: ∇ψ = Im(conj(R) ∇R) / |R|².
        kk = np.imag(np.conj(r)[..., None] * dr) / np.maximum(np.abs(r) ** 2, 1e-30)[..., None]
        good = _sane_wavevectors(kk) & np.all(
            np.abs(np.log(np.linalg.norm(kk, axis=2) / np.linalg.norm(k0, axis=2))) < 0.5, axis=1
        )
        ok &= good
        k = np.where(good[:, None, None], kk, k)
        psi = np.angle(-r)  # tag centres at phase 0
        kinv = np.linalg.inv(np.where(ok[:, None, None], k, np.eye(2)))
        step = -np.einsum('nad,nd->na', kinv, psi)
        x = np.where(ok[:, None], x + np.clip(step, -1.0, 1.0), x)
        mag = np.abs(r) / np.maximum(gsum, 1e-12)
    return x, mag, ok


def _tuned_response(windows, shape, patch, x, k, sigmas):
    """
    Tuned responses at ``x`` by direct summation over each point's patch, (R, ∇R, Σg).

    ``windows`` are the padded image's and its inside mask's patch views, ``patch`` the patch
    offsets (px) and half width; ``k`` the (N, 2, 2) wave vectors, rad/px. R is (N, 2) complex,
    ∇R (N, 2, 2) per px and Σg the envelopes' sums (N, 2).
    """
    win_img, win_in = windows
    o, half = patch
    n = 2 * half + 1
    sigma_u, sigma_v = sigmas
    kn = np.linalg.norm(k, axis=2)
    safe_kn = np.where(kn > 0, kn, 1.0)
    u = k / safe_kn[..., None]  # unit wave vectors (N, 2, 2)
    v = np.stack([-u[..., 1], u[..., 0]], -1)
    lam = 2 * np.pi / safe_kn
    su = (sigma_u * lam)[..., None]
    sv = (sigma_v * lam)[..., None]
    q = np.clip(np.rint(x).astype(int), -half - 1, np.array(shape) + half)
    corner = q - half + n  # the patch's first pixel in the padded image
    vals = win_img[corner[:, 0], corner[:, 1]]  # (N, n, n)
    inside = win_in[corner[:, 0], corner[:, 1]]
    # Single precision for the (N, 2, n, n) work arrays (positions stay float64; the sums
    # are over ≤ 10³ terms, far from float32 round-off at the 10⁻³ px level). Every term is
    # separable in the patch offsets: δ = p − y = (q − y) + (a, b), so the projections
    # δ·u, δ·v and the carrier e^{−ik·δ} are built from per-row and per-column factors.
    d0 = (q - x).astype(np.float32)  # (N, 2)
    u32, v32, k32 = (z.astype(np.float32) for z in (u, v, k))

    def along(e):  # e·δ for each direction, (N, 2, n, n)
        base = np.einsum('nda,na->nd', e, d0)[..., None, None]
        return base + e[..., 0, None, None] * o[:, None] + e[..., 1, None, None] * o

    du, dv = along(u32), along(v32)
    g = np.exp(
        -0.5 * (du / su[..., None].astype(np.float32)) ** 2
        - 0.5 * (dv / sv[..., None].astype(np.float32)) ** 2
    )
    g *= inside[:, None]
    e_row = np.exp(-1j * (k32[..., 0, None] * o)).astype(np.complex64)  # (N, 2, n)
    e_col = np.exp(-1j * (k32[..., 1, None] * o)).astype(np.complex64)
    e_row *= np.exp(-1j * np.einsum('nda,na->nd', k32, d0)).astype(np.complex64)[..., None]
    carrier = e_row[..., :, None] * e_col[..., None, :]  # e^{−ik·δ}, (N, 2, n, n)
    # Convolution R(y) = Σ_p h(y − p) I(p), h(x) = g(x)(e^{ik·x} − c): same sign as the bank.
    gsum = np.sum(g, axis=(2, 3))
    c = np.sum(g * carrier, axis=(2, 3)) / np.maximum(gsum, 1e-12)
    gv = g * vals[:, None]
    gvc = gv * carrier
    wgt = gvc - c[..., None, None] * gv
    r = np.sum(wgt, axis=(2, 3)).astype(np.complex128)  # (N, 2)
    # ∇_y h(y − p) = g (u du/su² + v dv/sv²)(e^{−ik·δ} − c) + i k g e^{−ik·δ}
    dr = (
        np.sum(wgt * du, axis=(2, 3))[..., None] / su**2 * u
        + np.sum(wgt * dv, axis=(2, 3))[..., None] / sv**2 * v
        + 1j * k * np.sum(gvc, axis=(2, 3))[..., None]
    )  # (N, 2, 2)
    return r, dr.astype(np.complex128), gsum


def _sane_wavevectors(k: np.ndarray) -> np.ndarray:
    """Both wave vectors longer than 2π/64 rad/px and at least ~12° from parallel, (N,) bool."""
    kn = np.linalg.norm(k, axis=2)
    det = k[:, 0, 0] * k[:, 1, 1] - k[:, 0, 1] * k[:, 1, 0]
    return np.all(kn > 2 * np.pi / 64, axis=1) & (np.abs(det) > 0.2 * kn[:, 0] * kn[:, 1])


def detect_intersections(
    image,
    mask=None,
    spacing_px=None,
    angles=None,
    *,
    params: TagParameters | None = None,
    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
    min_energy_fraction: float = 0.1,
    orientations_deg=(-12.0, 0.0, 12.0),
    spacing_factors=(0.8, 1.0, 1.25),
    sigma_u: float = 0.5,
    sigma_v: float = 0.6,
    max_residual: float = 0.3,
    roi=None,
    accept_mask=None,
    normalise: bool = True,
    tuned: bool | None = None,
    keep_maps: bool = False,
    coverage_normalised: bool = False,
    max_tuned_move_periods: float | None = None,
    spacing_range_px: tuple[float, float] = (MIN_SPACING_PX, MAX_SPACING_PX),
) -> Detection:
    """
    Find tag-grid intersections with sub-pixel accuracy (stateless; never raises on bad images).

    Parameters
    ----------
    image : array_like, shape (H, W)
        One tagged frame (any real dtype).
    mask : array_like of bool, shape (H, W), optional
        Myocardium; points whose nearest pixel is outside are dropped. Without a mask, points are
        kept where the tag energy ``|R_1||R_2|`` is at least ``min_energy_fraction`` of its 99th
        percentile (blood pool and air carry no tags).
    spacing_px : float or (2,) floats, optional
        Tag spacing override, px; estimated from the spectrum when omitted.
    angles : (2,) floats, optional
        Wave-vector angle overrides, rad (see :mod:`mlv_ros.core.tags.gabor`).
    params : TagParameters, optional
        Complete parameters (take precedence over ``spacing_px``/``angles``), e.g. the ED values a
        tracker reuses at later phases when tags are too deformed or faded for the spectrum.
    min_confidence : float
        Minimum confidence (0..1) of a kept point.
    min_energy_fraction : float
        See ``mask``.
    orientations_deg, spacing_factors, sigma_u, sigma_v
        Filter bank, see :func:`mlv_ros.core.tags.gabor.kernel_bank`.
    max_residual : float
        Largest phase residual after refinement, rad.
    roi : (row0, row1, col0, col1), optional
        Only look for points in ``image[row0:row1, col0:col1]`` (filtering runs on that window
        plus a margin of three envelope widths, which is what makes a 256² frame cheap). Default:
        the mask's bounding box when a mask is given, else the whole image.
    accept_mask : array_like of bool, shape (H, W), optional
        Where points may lie, if different from ``mask`` (e.g. a tracker filters with an
        eroded, uncertain mask but accepts points up to its original border).
    normalise : bool
        With a mask, filter ``mask·(I − masked local mean)`` instead of ``I``
        (see :func:`masked_normalise`); removes the blood-pool edge bias.
    tuned : bool, optional
        Finish with :func:`refine_tuned` (kernels tuned to each point's local wave vectors).
        Default: only with a mask, whose border truncates the tags and makes the bank's
        quantised tuning matter; on an untruncated grid the bank's phase is already unbiased
        and tuning every point of a whole frame would cost ~0.2 ms per point.
    keep_maps : bool
        Attach the :class:`GaborMaps` (of the filtered window) to the result.
    coverage_normalised : bool
        With a mask (and ``normalise``), divide the confidence by ``sqrt(c)``, ``c`` the share of
        the filter's energy envelope (Gaussian, 0.4 tag spacings) inside the mask (floored at
        COVERAGE_FLOOR). The masked image is zero outside the mask, so a wall thinner than the
        filter gives a response ∝ c from its tags but ∝ sqrt(c) from noise: the plain confidence
        then rejects thin-wall tags that stand as far above the noise as thick-wall ones do.
        Normalised, noise scores the same whatever the wall thickness, and one threshold is one
        false-alarm rate (thick walls, c ≈ 1, are unchanged). Used to follow known tracks.
    max_tuned_move_periods : float, optional
        Largest move of the tuned refinement, in tag periods (default ``TUNED_MAX_MOVE_PX``
        pixels); a point moved farther is dropped.
    spacing_range_px : (float, float)
        Tag periods the spectrum estimate considers, px (:func:`estimate_grid`).

    Returns
    -------
    Detection
        Empty with ``reason`` set when the image is unusable or holds no intersection.

    Notes
    -----
    Cost: one FFT plus one inverse FFT per kernel (18 by default) and O(H·W) vector operations.

    """
    checked = _checked_inputs(image, mask, params, spacing_px, angles, spacing_range_px)
    if isinstance(checked, Detection):
        return checked
    img, m, params = checked
    reason = _unusable_grid(params, img.shape, spacing_factors)
    if reason:
        return Detection(params=params, reason=reason)
    window = _filter_window(img.shape, roi, m, params, sigma_u, sigma_v, spacing_factors)
    if isinstance(window, str):
        return Detection(params=params, reason=window)
    cropped = _cropped(img, m, accept_mask, roi, window)
    if isinstance(cropped, str):
        return Detection(params=params, reason=cropped)
    full_shape = img.shape
    img, m, acc = cropped
    bank = (orientations_deg, spacing_factors, sigma_u, sigma_v)
    img, maps, conf, plain = _filtered(img, m, params, bank, normalise, coverage_normalised)
    kept_maps = maps if keep_maps else None
    # ψ_d = wrap(φ_d − π): multiply by −1 so that tag centres have phase 0.
    field_ = PhaseField.from_complex(-maps.response)
    valid, det = _valid_pixels(field_, conf, min_confidence, acc, m)
    if mask is None:
        energy = maps.magnitude[0] * maps.magnitude[1]
        valid &= energy >= min_energy_fraction * np.percentile(energy, 99)
    if not valid.any():
        return Detection(
            params=params,
            reason=f'no pixel with tag confidence ≥ {min_confidence:g}'
            + (' inside the mask' if m is not None else '')
            + ': no tags or tags faded',
            maps=kept_maps,
        )
    start = _newton_starts(field_, valid, det)
    if start.shape[0] == 0:
        return Detection(
            params=params,
            reason='no tag intersection found (phases never both ≡ π)',
            maps=kept_maps,
        )
    x, res, q = _refined(field_, start, valid, max_residual)
    if tuned is None:
        tuned = mask is not None
    if tuned and len(x):
        limit = (
            TUNED_MAX_MOVE_PX
            if max_tuned_move_periods is None
            else float(max_tuned_move_periods) * float(np.mean(params.spacing_px))
        )
        x, res, q = _tuned_pass(img, field_, valid, (x, res, q), (sigma_u, sigma_v), limit)
    if x.shape[0] == 0:
        return Detection(
            params=params,
            reason='no tag intersection passed refinement '
            f'(residual ≤ {max_residual:g} rad, confidence ≥ {min_confidence:g})',
            maps=kept_maps,
        )
    pts = _distinct_roots(x, res, conf[q[:, 0], q[:, 1]], plain[q[:, 0], q[:, 1]])
    offset = np.array([window[0], window[2]], float)
    return _labelled_detection(pts, offset, full_shape, params, kept_maps)


def _checked_inputs(image, mask, params, spacing_px, angles, spacing_range_px):
    """Validate the image and mask, resolve the grid: (img, mask, params) or a Detection."""
    try:
        img = validate_image(image)
        m = None
        if mask is not None:
            m = np.asarray(mask, bool)
            if m.shape != img.shape:
                return Detection(
                    reason=f'mask shape {m.shape} differs from image shape {img.shape}'
                )
            if not m.any():
                return Detection(reason='mask is empty')
        if params is None:
            est_mask = (
                None
                if m is None
                else cv2.dilate(m.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
            )
            params = resolve_parameters(
                img,
                est_mask,
                spacing_px,
                angles,
                estimate=lambda im, mk: estimate_grid(
                    im,
                    mk,
                    score_region=None if mk is None else m,
                    spacing_range_px=spacing_range_px,
                ),
            )
    except TagInputError as exc:
        return Detection(reason=str(exc))
    return img, m, params


def _unusable_grid(params: TagParameters, shape, spacing_factors) -> str:
    """Say why the bank cannot resolve this grid (spacing or directions), '' when it can."""
    if np.any(params.spacing_px < 4.0 / max(spacing_factors)) or np.any(
        params.spacing_px > min(shape) / 2
    ):
        return (
            f'tag spacing {params.spacing_px} px outside the usable range '
            f'[{4.0 / max(spacing_factors):.1f}, {min(shape) / 2:.0f}] px'
        )
    sep = abs(np.angle(np.exp(2j * (params.angles[0] - params.angles[1])))) / 2
    if sep < np.deg2rad(30):
        return f'tag directions only {np.rad2deg(sep):.1f}° apart (need ≥ 30°)'
    return ''


def _filter_window(shape, roi, m, params, sigma_u, sigma_v, spacing_factors):
    """Filter only the region of interest plus a margin, (r0, r1, c0, c1) px or why not."""
    h, w = shape
    if roi is None and m is not None:
        rows, cols = np.nonzero(m)
        roi = (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1)
    if roi is None:
        return 0, h, 0, w
    # Margin: three envelope standard deviations of the widest kernel keep the circular
    # convolution of the cropped FFT from wrapping into the region of interest.
    margin = (
        int(
            np.ceil(
                3 * max(sigma_u, sigma_v) * max(spacing_factors) * float(np.max(params.spacing_px))
            )
        )
        + 2
    )
    r0, r1, c0, c1 = (int(v) for v in roi)
    r0, c0 = max(0, r0 - margin), max(0, c0 - margin)
    r1, c1 = min(h, r1 + margin), min(w, c1 + margin)
    if r1 - r0 < 16 or c1 - c0 < 16:
        return f'region of interest {roi} too small or outside the image'
    return r0, r1, c0, c1


def _cropped(img, m, accept_mask, roi, window):
    """Crop image, mask and accept mask to the filter window, (img, m, acc) or why not."""
    r0, r1, c0, c1 = window
    full_shape = img.shape
    img = img[r0:r1, c0:c1]
    acc = None
    if accept_mask is not None:
        acc = np.asarray(accept_mask, bool)
        if acc.shape != full_shape:
            return f'accept_mask shape {acc.shape} differs from image shape {full_shape}'
        acc = acc[r0:r1, c0:c1]
    if m is not None:
        m = m[r0:r1, c0:c1]
    elif roi is not None:
        # Points only inside the requested window (not in its filtering margin).
        m = np.zeros(img.shape, bool)
        m[int(roi[0]) - r0:int(roi[1]) - r0, int(roi[2]) - c0:int(roi[3]) - c0] = True
    return img, m, acc


def _filtered(img, m, params, bank, normalise, coverage_normalised):
    """Run the bank on the window (normalised with a mask), (img filtered, maps, conf, plain)."""
    orientations_deg, spacing_factors, sigma_u, sigma_v = bank
    std = None
    if m is not None and normalise:
        img, std = masked_normalise(img, m, float(np.mean(params.spacing_px)))
    maps = gabor_filter_bank(img, params, orientations_deg, spacing_factors, sigma_u, sigma_v)
    conf = plain = confidence_map(img, maps, params, std)
    if std is not None and coverage_normalised:
        lam = float(np.mean(params.spacing_px))
        cov = cv2.GaussianBlur(
            m.astype(np.float32), (0, 0), 0.4 * lam, borderType=cv2.BORDER_CONSTANT
        )
        conf = np.minimum(plain / np.sqrt(np.maximum(cov, COVERAGE_FLOOR)), 1.0).astype(np.float32)
    return img, maps, conf, plain


def _valid_pixels(field_: PhaseField, conf, min_confidence, acc, m):
    """Pixels whose phase Jacobian is well conditioned and confidence high enough, (valid, det)."""
    j = field_.jac
    det = j[0, 0] * j[1, 1] - j[0, 1] * j[1, 0]
    scale = np.hypot(j[0, 0], j[0, 1]) * np.hypot(j[1, 0], j[1, 1])
    valid = (np.abs(det) > 0.2 * scale) & (scale > 0) & (conf >= min_confidence)
    if acc is not None:
        valid &= acc
    elif m is not None:
        valid &= m
    return valid, det


def _newton_starts(field_: PhaseField, valid, det) -> np.ndarray:
    """Roots predicted by one Newton step that fall in their own pixel's cell, (N, 2) px."""
    rr, cc = np.nonzero(valid)
    psi = field_.psi_at(rr, cc).T
    jj = np.moveaxis(field_.jac[:, :, rr, cc], -1, 0)
    dd = det[rr, cc]
    # One Newton step from each pixel: δ = −J⁻¹ψ; keep pixels whose predicted root is in its cell.
    step = (
        -np.stack(
            [
                jj[:, 1, 1] * psi[:, 0] - jj[:, 0, 1] * psi[:, 1],
                -jj[:, 1, 0] * psi[:, 0] + jj[:, 0, 0] * psi[:, 1],
            ],
            -1,
        )
        / dd[:, None]
    )
    cand = np.all(np.abs(step) <= 0.55, axis=1)
    return np.stack([rr, cc], -1)[cand] + step[cand]


def _refined(field_: PhaseField, start, valid, max_residual):
    """Newton-refine the starts on the bank's phases, keep converged valid ones, (x, res, q)."""
    x, res, ok = solve_phase(field_, start, iterations=3, max_step=1.0)
    q, inside = field_.nearest(x)
    keep = ok & inside & (res <= max_residual)
    keep &= valid[q[:, 0], q[:, 1]]
    return x[keep], res[keep], q[keep]


def _tuned_pass(img, field_: PhaseField, valid, points, sigmas, limit):
    """Re-locate points with tuned kernels, dropping those moved beyond ``limit`` px."""
    x, res, q = points
    kloc = np.moveaxis(
        field_.jac[:, :, q[:, 0], q[:, 1]], -1, 0
    )  # (N, 2, 2) local wave vectors
    xt, _, okt = refine_tuned(img, x, kloc, *sigmas)
    # A refinement that moves a point far means the two filters disagree (clutter, wrong
    # tuning): drop the point rather than guess.
    moved = np.linalg.norm(xt - x, axis=1)
    qt, inside_t = field_.nearest(xt)
    keep = okt & (moved <= limit) & inside_t & valid[qt[:, 0], qt[:, 1]]
    return xt[keep], res[keep], qt[keep]


def _distinct_roots(x, res, c, cp):
    """Keep the most confident of points within 1 px (neighbours converge to one root)."""
    order = np.argsort(-c, kind='stable')
    x, res, c, cp = x[order], res[order], c[order], cp[order]
    drop = np.zeros(len(x), bool)
    for a, b in sorted(cKDTree(x).query_pairs(1.0)):
        if not drop[a]:
            drop[b] = True
    return x[~drop], res[~drop], c[~drop], cp[~drop]


def _labelled_detection(points, offset, full_shape, params, maps) -> Detection:
    """Label window points on the grid, back in full-image px, in a deterministic order."""
    x, res, c, cp = points
    x = x + offset
    labels = grid_labels(x, params, full_shape, weights=c)
    # Deterministic order: by label, then position.
    order = np.lexsort((x[:, 1], x[:, 0], labels[:, 1], labels[:, 0]))
    return Detection(
        pixel_rc=x[order],
        labels=labels[order],
        confidence=c[order].astype(np.float32),
        residual=res[order].astype(np.float32),
        plain_confidence=cp[order].astype(np.float32),
        params=params,
        reason='',
        maps=maps,
    )

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
Automatic end-diastolic LV myocardium segmentation on tagged SA and LA images.

Why tag energy: SPAMM tags are laid down at end-diastole in all tissue, but flowing blood carries
them out of the slice within tens of milliseconds, so at ED the myocardium is *tagged*, the
blood pool is *untagged*, and the surroundings are either tagged (static tissue, more weakly
than the wall) or dark (studies that tag only the heart, air, lung). Neither intensity order nor
grid orientation is assumed: blood may be brighter or darker than the tagged wall's mean, the
grid may lie at any angle, and every level is taken from the image itself (no absolute
intensity anywhere, so scaling an image changes nothing). Two local features (pixel units):

* ``energy`` E — the tag amplitude. The two tag wave vectors come from the spectrum (peaks in
  the band of plausible periods); the tag-free mean (below) is subtracted and a complex Gabor
  filter (Gaussian envelope σ = λ/2, which passes the grid's other harmonics at ≈ 0.7 %) is
  demodulated at each. A bright pool beside the wall (the right ventricle) can out-weigh the
  tags in the plain spectrum; the segmenters also try the whitened one
  (:func:`candidate_features`) and keep the estimate under which the wall stands out most. At
  ED the grid is undeformed, so the tags have one phase per direction over the whole image: E is
  the sum of the responses projected on those phases.
  That keeps the tags' amplitude, linear in the tagged fraction of a pixel, while most of the
  response to intensity steps — a bright blood pool's edge has spectral content in the tag
  band — has the phase of the edge's position and cancels;
* ``mean`` M — the average over one cell of the tag lattice (its transfer function vanishes on
  every harmonic of the grid): the tag-free local mean, linear in the tissue fractions.

Walls along rays (:func:`_wall_runs`): from a point in the cavity, each ray's first energy run
is the wall; the cavity and outside levels come from the samples before and beyond it. A first
estimate thresholds each ray's energy profile where the edges of a Gaussian-blurred wall of the
width it shows lie (½ of the peak for a thick wall, more for a thin one); then both features
are fitted together by least squares (:func:`_fit_walls`), each as cavity level, wall plateau
and outside level blurred at the two edges: the mean is sharper and untouched by steps, the
energy carries the wall wherever blood and wall have the same mean. The cavity level is one (one
blood pool); the mean's outside level is each ray's own, read just beyond its wall: beside the
septum lies the right ventricle's bright untagged blood, elsewhere lung, liver or chest wall.
Edges are the partial-volume boundary (fraction 0.5, the ground-truth convention).

Shape prior (paper §3.2 relies on a segmentation of both views; we use a geometric prior
instead of the paper's learned one):

* SA — a star-shaped annulus around the blood pool found at the long axis: rays from the axis
  point, one wall per ray, radii smoothed over angle.
* LA — the horseshoe: rays from a point on the long axis inside the cavity; rays toward the base
  find no myocardium (atrium), the contiguous arc that does is the horseshoe, cut flat at the
  base level perpendicular to the axis. Stretches of wall too faint for the energy (tagged
  surroundings) are bridged where the geometry rules out the opening (:func:`_la_from_runs`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import functools

from mlv_ros.core.filters import running_median
from mlv_ros.core.tags.gabor import TAG_PERIOD_RANGE_MM  # plausible SPAMM periods, mm
from mlv_ros.core.types import TAGS_LINE_PAIR, TAGS_LINES
import numpy as np
from scipy import ndimage as ndi
from scipy.special import ndtr

#: Rays per slice (2° apart).
NUM_RAYS = 180
#: Radial sampling step along a ray, px.
RADIAL_STEP_PX = 0.25
#: LA: gaps in the horseshoe up to this wide are bridged, deg (the atrium's opening is wider).
LA_MAX_GAP_DEG = 10.0
#: LA: the horseshoe's side ends before this many consecutive rays (2° apart) that are thinner
#: than ``LA_THIN_END_FRACTION`` of its median wall or met nothing (:func:`_thin_ends_cut`):
#: the atrium's edge past the base is a step, thinner than any ventricular wall.
LA_THIN_END_RAYS = 3
LA_THIN_END_FRACTION = 0.5
#: Shortest tag period resolved, px.
MIN_TAG_PERIOD_PX = 2.5
#: Gaussian envelope of the tag-energy filter, in tag periods: σ = λ/2 passes the grid's
#: neighbouring harmonics (one period⁻¹ away) at e^{-π²/2} ≈ 0.7 %.
ENERGY_SIGMA_PERIODS = 0.5
#: Blur of the wall's edges in the energy, in filter σ: the demodulated tag amplitude of a wall
#: not much thicker than a period also carries the response to the wall's own mean (its edges
#: are intensity steps), which widens it. Measured on the simulator (walls 6–17 mm, periods
#: 5–10 mm): 1.3 σ against σ, mean SA / LA Dice: normal LV 0.939 / 0.921 → 0.949 / 0.936,
#: 6 mm wall 0.891 / 0.873 → 0.918 / 0.908, 17 mm wall 0.976 / 0.947 → 0.973 / 0.944.
ENERGY_EDGE_BLUR = 1.3
#: The wall's tag energy must exceed the cavity's and the surroundings' by this factor, and by
#: this many times the energy's noise (:attr:`TagFeatures.noise`). Measured: pure noise images
#: (white, smoothed, Rician) reach at most 3.6; the simulated walls at least 6.7 (a 6 mm wall
#: under a 9.4 mm grid in surroundings tagged at 0.45), 12 for a normal LV at SNR 10.
MIN_ENERGY_CONTRAST = 1.3
MIN_WALL_SNR = 4.5
#: Wall refinement (:func:`_fit_walls`): iterations, and how far each edge may move per
#: iteration, px.
REFINE_ITERATIONS = 3
REFINE_REACH_PX = 3.0
#: Each ray's own outside level (:func:`_fit_walls`) is read between these distances beyond its
#: epicardium, in the channel's edge blur σ: past the blurred edge (Φ(−1.8) ≈ 4 % of the wall
#: left), and within about one more edge width, so that what lies just outside the wall — the
#: right ventricle's blood on the septal side, lung or tagged tissue elsewhere — sets it.
OUTSIDE_NEAR_SIGMA = (1.8, 3.6)


@dataclass
class TagFeatures:
    """
    Tag-energy features of one image (see module docstring).

    Attributes
    ----------
    energy : ndarray, shape (rows, cols)
        Local tag amplitude E (image intensity units): each direction's demodulated Gabor
        response projected on its phase, summed (module docstring).
    mean : ndarray, shape (rows, cols)
        Tag-free local mean intensity M (average over one cell of the tag lattice).
    wavelength_px : float
        Tag period λ (mean of the directions), px.
    wavevectors : ndarray, shape (F, 2)
        (row, col) spatial frequencies of the F tag directions (2: a grid, 1: one family of
        tag lines), cycles / px.
    blur_px : float
        Gaussian σ of the energy filter, px: the blur of an edge in ``energy``.
    noise : float
        Standard deviation of the noise in ``energy`` (robust spread of the quadrature part,
        which holds no tags), energy units.

    """

    energy: np.ndarray
    mean: np.ndarray
    wavelength_px: float
    wavevectors: np.ndarray
    blur_px: float = 0.0
    noise: float = 0.0


@dataclass
class SliceSegmentation:
    """
    Myocardium of one slice, in polar form around ``centre_rc`` plus the pixel mask.

    Attributes
    ----------
    ok : bool
    reason : str
        Empty when ``ok``; otherwise why the slice was rejected.
    mask : ndarray of bool, shape (rows, cols)
        Myocardium (all False when not ``ok``).
    centre_rc : ndarray, shape (2,)
        Ray origin, (row, col) px.
    angles : ndarray, shape (K,)
        Ray angles θ, rad; a ray points along (sin θ, cos θ) in (row, col).
    endo, epi : ndarray, shape (K,)
        Endocardial / epicardial radius per ray, px (NaN on rays without myocardium, e.g. the
        LA rays toward the atrium). ``endo == 0`` where there is no cavity (apical slices).
    view : str
        ``"SA"`` or ``"LA"``.
    base_level : float
        LA only: base-plane cut as a coordinate along ``axis_rc`` from ``centre_rc``, px; NaN
        when the view does not show it (a horseshoe closed over the atrium).
    axis_rc : ndarray, shape (2,)
        LA only: unit in-plane long-axis direction (apex → base), (row, col).
    source : str
        ``"auto"`` (this module) or ``"mask"`` (user label image).

    """

    ok: bool
    reason: str
    mask: np.ndarray
    centre_rc: np.ndarray = field(default_factory=lambda: np.zeros(2))
    angles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    endo: np.ndarray = field(default_factory=lambda: np.zeros(0))
    epi: np.ndarray = field(default_factory=lambda: np.zeros(0))
    view: str = 'SA'
    base_level: float = np.inf
    axis_rc: np.ndarray = field(default_factory=lambda: np.zeros(2))
    source: str = 'auto'


# --------------------------------------------------------------------------- features
def tag_families(tag_lines: int) -> int:
    """
    Tag directions in a frame's ``image``: 1 for one family of tag lines, else 2 (a grid).

    ``tag_lines`` is ``Frame.tag_lines``; a line pair's ``image`` holds one family too (its
    partner series is ``line_image``).
    """
    return 1 if tag_lines in (TAGS_LINES, TAGS_LINE_PAIR) else 2


def tag_period_band_px(pixel_spacing_mm: float | None) -> tuple[float, float]:
    """
    Search band of tag periods for :func:`tag_wavevectors`, px.

    With a pixel spacing: :data:`TAG_PERIOD_RANGE_MM` in pixels (never below
    :data:`MIN_TAG_PERIOD_PX`); without one: 2.5–30 px.
    """
    if pixel_spacing_mm is None or not np.isfinite(pixel_spacing_mm) or pixel_spacing_mm <= 0:
        return MIN_TAG_PERIOD_PX, 30.0
    lo = max(MIN_TAG_PERIOD_PX, TAG_PERIOD_RANGE_MM[0] / pixel_spacing_mm)
    return lo, max(TAG_PERIOD_RANGE_MM[1] / pixel_spacing_mm, lo + 1.0)


def tag_wavevectors(
    image: np.ndarray,
    min_period_px: float = MIN_TAG_PERIOD_PX,
    max_period_px: float = 30.0,
    whitened: bool = False,
) -> np.ndarray:
    """
    Estimate the two dominant tag wave vectors from the windowed magnitude spectrum.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        Tagged image (intensity, any scale).
    min_period_px, max_period_px : float
        Search band of tag periods, px. Keep the upper end near the longest plausible period
        (:func:`tag_period_band_px`): below it, the spectrum of a bright blood pool's outline
        (which falls off as 1/frequency) can out-weigh the tags.
    whitened : bool
        Search the spectrum times the frequency: an intensity step's spectrum falls off as
        1/frequency, so its in-band maximum sits at the band's long-period end, where a bright
        pool next to the wall (the right ventricle's blood crescent, thinner than the median
        window below) can out-weigh the tags; whitened, a step is flat over the band and the
        tags' peak stands out, at the cost of favouring the grid's higher harmonics.
        :func:`segment_sa` / :func:`segment_la` try both (:func:`candidate_features`).

    Returns
    -------
    ndarray, shape (2, 2)
        (row, col) frequencies in cycles / px; the second direction is ≥ 30° from the first.
        Peaks are refined to sub-bin precision by parabolic interpolation.

    Notes
    -----
    The spectrum is taken of the image less its running median over a window of the longest
    period: the median follows a large uniform region (a bright blood pool, the LA views'
    cavity with its flat basal cut) edge and all, so its outline no longer reaches the tag band,
    while the tags, finer than the window, stay in the residual. Without it the outline of a
    blood pool brighter than the tagged wall out-weighed the tags in long-axis views (periods
    found 1.5–2.5 × too long, the energy then missing the thin apical wall).
    The peaks are refined on the image's own spectrum (the median takes a little of the tags
    too, unevenly across a peak's bins).

    """
    return _spectral_peaks(image, min_period_px, max_period_px, (whitened,))[0]


def _spectral_peaks(image, min_period_px, max_period_px, whitened):
    """
    :func:`tag_wavevectors` for each of the flags ``whitened``, from one pair of spectra.

    The running median and both FFTs depend on neither flag: computed once, shared.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        Tagged image (intensity, any scale).
    min_period_px, max_period_px : float
        Search band of tag periods, px.
    whitened : tuple of bool
        One search per flag (:func:`tag_wavevectors`).

    Returns
    -------
    list of ndarray, shape (2, 2)
        (row, col) frequencies in cycles / px, one per flag.

    """
    img = np.asarray(image, dtype=np.float64)
    win = np.outer(np.hanning(img.shape[0]), np.hanning(img.shape[1]))
    res = img - running_median(img, int(np.ceil(max_period_px)) | 1)
    found = np.abs(np.fft.fft2((res - res.mean()) * win))
    spec = np.abs(np.fft.fft2((img - img.mean()) * win))
    fy = np.fft.fftfreq(img.shape[0])
    fx = np.fft.fftfreq(img.shape[1])
    FY, FX = np.meshgrid(fy, fx, indexing='ij')
    fr = np.hypot(FY, FX)
    band = (fr >= 1.0 / max_period_px) & (fr <= 1.0 / min_period_px)
    return [_peak_pair(img.shape, found, spec, FY, FX, fr, band, w) for w in whitened]


def _peak_pair(shape, found, spec, FY, FX, fr, band, whitened):
    """Return the two refined spectral peaks of :func:`tag_wavevectors` (its arrays, one flag)."""
    s1 = np.where(band, found * fr if whitened else found, 0.0)
    i = np.unravel_index(int(np.argmax(s1)), s1.shape)
    k1 = np.array([FY[i], FX[i]])
    cosang = np.abs(FY * k1[0] + FX * k1[1]) / (fr * np.linalg.norm(k1) + 1e-12)
    s2 = np.where(cosang < np.cos(np.radians(30.0)), s1, 0.0)
    j = np.unravel_index(int(np.argmax(s2)), s2.shape)
    out = []
    for idx in (i, j):
        k = np.array([FY[idx], FX[idx]], dtype=np.float64)
        for ax, n in enumerate(shape):  # parabolic refinement per axis
            lo = list(idx)
            hi = list(idx)
            lo[ax] = (idx[ax] - 1) % n
            hi[ax] = (idx[ax] + 1) % n
            ym, y0, yp = spec[tuple(lo)], spec[idx], spec[tuple(hi)]
            den = ym - 2 * y0 + yp
            if den < 0:
                k[ax] += 0.5 * (ym - yp) / den / n
        out.append(k)
    return np.array(out)


def tag_features(
    image: np.ndarray, wavevectors: np.ndarray | None = None, pixel_spacing_mm: float | None = None
) -> TagFeatures:
    """
    Tag energy and tag-free mean of an image (module docstring).

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        Tagged image (intensity, any scale).
    wavevectors : ndarray, shape (2, 2) or (1, 2), optional
        (row, col) tag frequencies, cycles / px: a grid's two directions, or the one direction
        of a single family of tag lines; a grid's two estimated from the spectrum by default.
    pixel_spacing_mm : float, optional
        Narrows the spectral search to plausible tag periods (:func:`tag_period_band_px`).

    Returns
    -------
    TagFeatures

    Raises
    ------
    ValueError
        ``wavevectors`` not of shape (1, 2) or (2, 2), or not finite and non-zero.

    """
    img = np.asarray(image, dtype=np.float64)
    kv = (
        tag_wavevectors(img, *tag_period_band_px(pixel_spacing_mm))
        if wavevectors is None
        else np.asarray(wavevectors, dtype=np.float64)
    )
    if kv.ndim != 2 or kv.shape[0] not in (1, 2) or kv.shape[1] != 2:
        raise ValueError(f'wavevectors must have shape (1, 2) or (2, 2), got {kv.shape}')
    if not np.all(np.isfinite(kv)) or np.any(np.linalg.norm(kv, axis=1) <= 0):
        raise ValueError(f'wavevectors must be finite and non-zero, got {kv.tolist()}')
    lam = float(np.mean(1.0 / np.linalg.norm(kv, axis=1)))
    sigma = ENERGY_SIGMA_PERIODS * lam
    # Reflect-pad by two periods: the circular FFT filters then see a continuous border.
    pad = int(np.ceil(2.0 * lam)) + 1
    big = np.pad(img, pad, mode='reflect')
    spec = np.fft.fft2(big)
    fy = np.fft.fftfreq(big.shape[0])[:, None]
    fx = np.fft.fftfreq(big.shape[1])[None, :]
    inner = (slice(pad, pad + img.shape[0]), slice(pad, pad + img.shape[1]))
    # Tag-free mean: the average over one cell of the tag lattice, whose transfer function
    # sinc(f·a1) sinc(f·a2) (a1, a2 the cell's edge vectors, a_i·k_j = δ_ij) vanishes on every
    # harmonic n1 k1 + n2 k2 of the grid. One family of lines: the average over one period
    # across the lines (a1 = k1 / |k1|²), sinc(f·a1), vanishing on every harmonic n1 k1; along
    # the lines there is nothing to average out.
    cell = np.linalg.pinv(kv)
    box = np.ones((fy.shape[0], fx.shape[1]))
    for a in cell.T:
        box = box * np.sinc(fy * a[0] + fx * a[1])
    mean = np.real(np.fft.ifft2(spec * box))
    # Complex Gabor response of the mean-free image at each wave vector (Gaussian envelope σ),
    # demodulated: at ED the grid is undeformed, so the tags have one phase per direction all
    # over the image. Projecting on it keeps the tags' linear amplitude, while the response
    # to an intensity step (a bright blood pool's edge, whose spectrum reaches the tag band)
    # has the phase of the edge's position and mostly cancels.
    resid = np.fft.fft2(big - mean)
    rr = np.arange(big.shape[0])[:, None]
    cc = np.arange(big.shape[1])[None, :]
    energy = np.zeros(img.shape)
    quadrature = np.zeros(img.shape)
    for k in kv:
        g = np.exp(-2.0 * np.pi**2 * sigma**2 * ((fy - k[0]) ** 2 + (fx - k[1]) ** 2))
        z = (np.fft.ifft2(resid * g) * np.exp(-2j * np.pi * (k[0] * rr + k[1] * cc)))[inner]
        z = z * np.exp(-1j * _dominant_phase(z))
        energy += z.real
        quadrature += z.imag
    # The quadrature part holds no tags, only noise and, where the wave vector is a little off,
    # a slow phase ramp times the tag amplitude: its spread above scale 2λ is the noise.
    quadrature -= ndi.gaussian_filter(quadrature, 2.0 * lam)
    noise = 1.4826 * float(np.median(np.abs(quadrature - np.median(quadrature))))
    return TagFeatures(energy, mean[inner], lam, kv, sigma, noise)


def candidate_features(
    image: np.ndarray, pixel_spacing_mm: float | None = None, families: int = 2
) -> list[TagFeatures]:
    """
    :func:`tag_features` at the plain and the whitened spectral estimate (:func:`tag_wavevectors`).

    One entry when both estimates agree (every wave vector within 5 % of the other's, sign and
    order free), else two, plain first. The segmenters keep the one under which the wall stands
    out most (:func:`_best_of`): the right tag frequency gives the wall its largest tag energy
    over the noise, whichever spectrum found it.

    ``families``: 2 for a grid; 1 for one family of tag lines (``Frame.tag_lines`` is
    ``TAGS_LINES``), whose image has no second direction: the strongest peak of each estimate
    only. The grid's second peak, searched ≥ 30° away, would be noise or a blood pool's
    outline there; demodulated as if tags, it added energy where there are none and halved
    the period's share of the filter width (mean of a true and a wrong period).
    """
    if families not in (1, 2):
        raise ValueError(f'families must be 1 (tag lines) or 2 (a grid), got {families!r}')
    img = np.asarray(image, dtype=np.float64)
    band = tag_period_band_px(pixel_spacing_mm)
    a, b = (k[:families] for k in _spectral_peaks(img, *band, (False, True)))

    def close(x, y):
        return min(np.linalg.norm(x - y), np.linalg.norm(x + y)) <= 0.05 * np.linalg.norm(y)

    same = (
        close(a[0], b[0])
        if families == 1
        else (close(a[0], b[0]) and close(a[1], b[1])) or (close(a[0], b[1]) and close(a[1], b[0]))
    )
    return [tag_features(img, a)] if same else [tag_features(img, a), tag_features(img, b)]


def _best_of(results: list) -> 'SliceSegmentation':
    """
    Pick the segmentation to keep from ``(SliceSegmentation, wall contrast-to-noise)`` pairs.

    An ``ok`` one over a failure, then the highest wall contrast; the first failure's reason
    otherwise.
    """
    ok = [r for r in results if r[0].ok]
    if not ok:
        return results[0][0]
    return max(ok, key=lambda r: r[1])[0]


def _wall_cnr(levels, feat: TagFeatures) -> float:
    """Wall tag energy above the higher of cavity and outside, in units of the energy's noise."""
    if levels is None:
        return -np.inf
    return float(
        (levels.peak - max(levels.cavity, levels.outside)) / max(float(feat.noise), 1e-300)
    )


def _dominant_phase(z: np.ndarray) -> float:
    """Mode of the phase of ``z``, weighted by |z|² (72 bins, smoothed circularly), rad."""
    h, edges = np.histogram(np.angle(z), bins=72, range=(-np.pi, np.pi), weights=np.abs(z) ** 2)
    h = ndi.gaussian_filter1d(h, 1.5, mode='wrap')
    i = int(np.argmax(h))
    # Parabolic refinement of the peak bin.
    ym, y0, yp = h[i - 1], h[i], h[(i + 1) % h.size]
    den = ym - 2 * y0 + yp
    frac = 0.5 * (ym - yp) / den if den < 0 else 0.0
    return float(edges[0] + (i + 0.5 + frac) * (edges[1] - edges[0]))


def _otsu(values: np.ndarray) -> float:
    """Otsu threshold of a 1-D sample (256 bins)."""
    hist, edges = np.histogram(values, bins=256)
    mids = 0.5 * (edges[1:] + edges[:-1])
    w0 = np.cumsum(hist)
    w1 = w0[-1] - w0
    m0 = np.cumsum(hist * mids)
    mu0 = m0 / np.maximum(w0, 1)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1)
    return float(mids[int(np.argmax(w0 * w1 * (mu0 - mu1) ** 2))])


# --------------------------------------------------------------------------- rays
def _sample_rays(
    values: np.ndarray, centre_rc: np.ndarray, angles: np.ndarray, max_radius_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Bilinear samples of ``values`` along rays from ``centre_rc``.

    Returns
    -------
    radii : ndarray, shape (R,)
        Sample radii, px (step :data:`RADIAL_STEP_PX`).
    s : ndarray, shape (K, R)
        Samples (0 outside the image).
    inside : ndarray of bool, shape (K, R)
        Whether each sample lies inside the image.

    """
    radii = np.arange(0.0, max_radius_px, RADIAL_STEP_PX)
    dirs = np.stack([np.sin(angles), np.cos(angles)], 1)
    pts = centre_rc[None, None, :] + radii[None, :, None] * dirs[:, None, :]
    s = ndi.map_coordinates(values, [pts[..., 0], pts[..., 1]], order=1, mode='constant', cval=0.0)
    rows, cols = np.shape(values)
    inside = (
        (pts[..., 0] >= 0)
        & (pts[..., 0] <= rows - 1)
        & (pts[..., 1] >= 0)
        & (pts[..., 1] <= cols - 1)
    )
    return radii, s, inside


def _ray_runs(
    score: np.ndarray,
    centre_rc: np.ndarray,
    angles: np.ndarray,
    max_radius_px: float,
    min_wall_px: float,
    max_gap_px: float,
    threshold: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """
    First run of ``score > threshold`` along each ray from ``centre_rc`` (user masks).

    Returns
    -------
    endo, epi : ndarray, shape (K,)
        Sub-pixel radii (linear interpolation of the crossing), px; NaN where a ray has no run
        of at least ``min_wall_px``. Runs separated by gaps < ``max_gap_px`` are merged
        (noise). ``endo = 0`` when the run starts at the centre.

    """
    radii, s, _ = _sample_rays(score, centre_rc, angles, max_radius_px)
    return _runs_at(s, radii, threshold, min_wall_px, max_gap_px)


@dataclass
class WallLevels:
    """
    Tag-energy levels found along the rays of one slice (energy units).

    Attributes
    ----------
    peak : float
        Median peak of the wall over the rays.
    cavity : float
        Blood pool inside the wall (untagged: ~0); equals ``outside`` when the rays start in
        the wall (apical slices).
    outside : float
        Just beyond the epicardium: ~0 for dark surroundings, a fraction of the wall's level
        where the surroundings are tagged.
    blur_px : float
        Blur of the wall's edges in the energy (Gaussian σ), px.

    """

    peak: float
    cavity: float
    outside: float
    blur_px: float


def _wall_runs(
    feat: TagFeatures,
    centre_rc: np.ndarray,
    angles: np.ndarray,
    max_radius_px: float,
    min_wall_px: float,
    max_gap_px: float,
):
    """
    Myocardial wall along each ray from ``centre_rc``.

    Every level comes from the rays themselves, so nothing depends on the intensity scale, on
    how bright blood or surroundings are, or on the wall's thickness against the blur:

    1. detection on the tag energy: the first run above the midpoint between the rays' typical
       peak and the higher of the cavity and outside levels (0 at first; three rounds);
    2. levels: the cavity from the samples ≥ 2σ before each run, the outside from one period
       of samples ≥ 2σ beyond it (or the end of rays whose run did not end: tagged
       surroundings above the first threshold);
    3. first walls: each ray's width at half its peak's excess over the two levels gives the
       width of a blurred wall with that profile, whose edges lie at the fraction
       :func:`_edge_fraction` of the excess (a thin wall's edges sit higher than half-way);
    4. least-squares refinement (:func:`_fit_walls`) on the energy and the tag-free mean
       together: the mean is linear in the tissue fractions and sharper, and where blood is
       bright its step carries the endocardium that the energy alone would blur.

    Returns
    -------
    endo, epi : ndarray, shape (K,)
        As :func:`_ray_runs` (NaN: no wall on that ray).
    levels : WallLevels or None
        None when the energy is flat (no wall stands out).

    """
    radii, s, inside = _sample_rays(feat.energy, centre_rc, angles, max_radius_px)
    sig = ENERGY_EDGE_BLUR * max(float(feat.blur_px), RADIAL_STEP_PX)
    lam = float(feat.wavelength_px)
    n_rays = s.shape[0]
    nan = np.full(n_rays, np.nan)
    found = _detected_levels(s, radii, inside, sig, lam, min_wall_px, max_gap_px)
    if found is None:
        return nan, nan, None
    endo, epi, ok, (top, cavity, outside), (cav, out) = found
    levels = WallLevels(top, cavity, outside, sig)
    noise = float(feat.noise)
    if not (
        top > MIN_ENERGY_CONTRAST * max(cavity, outside, 0.0)
        and top - max(cavity, outside) > MIN_WALL_SNR * noise
    ):
        return endo, epi, None
    rows = np.flatnonzero(ok)
    sub = s[rows]
    sig0 = max(float(feat.blur_px), RADIAL_STEP_PX)
    e, q = _first_walls(sub, radii, endo[rows], epi[rows], (cavity, outside), sig0, min_wall_px)
    # Cavity samples again from these walls: a small cavity (apical slices) may sit above the
    # detection threshold, blurred by the wall around it, yet be a cavity.
    ei = (e / RADIAL_STEP_PX).astype(int)
    idx = np.arange(s.shape[1])
    cav_rows = (
        idx[None, :] < np.minimum(ei - int(round(2.0 * sig0 / RADIAL_STEP_PX)), ei // 2)[:, None]
    ) & inside[rows]
    if cav_rows.any(axis=1).sum() >= 0.25 * rows.size and cav_rows.sum() >= 20:
        cav = np.zeros_like(cav)
        cav[rows] = cav_rows
    _, sm, _ = _sample_rays(feat.mean, centre_rc, angles, max_radius_px)
    e, q = _fit_walls(
        (
            (sub, sig, float(feat.blur_px), False),
            (sm[rows], lam / np.sqrt(12.0), lam / np.sqrt(12.0), True),
        ),
        radii,
        e,
        q,
        cav[rows],
        out[rows],
        min_wall_px,
        inside[rows],
    )
    endo = np.full(n_rays, np.nan)
    epi = np.full(n_rays, np.nan)
    good = (q - e) >= min_wall_px
    endo[rows[good]] = e[good]
    epi[rows[good]] = q[good]
    return endo, epi, levels


def _detected_levels(s, radii, inside, sig, lam, min_wall_px, max_gap_px):
    """
    Detect the wall runs and their levels in three rounds (steps 1-2 of :func:`_wall_runs`).

    Returns ``(endo, epi, ok, (peak, cavity, outside), (cavity samples, outside samples))``, or
    None when fewer than half the rays see anything or fewer than 5 rays hold a run.
    """
    n_rays, n = s.shape
    peaks = np.where(inside, s, -np.inf).max(axis=1)
    if np.isfinite(peaks).sum() < n_rays // 2:
        return None
    top = float(np.percentile(peaks[np.isfinite(peaks)], 70))
    if not top > 0:
        return None
    idx = np.arange(n)
    last = np.where(inside.any(axis=1), n - 1 - np.argmax(inside[:, ::-1], axis=1), 0)
    span = max(int(round(lam / RADIAL_STEP_PX)), 4)
    off = int(round(2.0 * sig / RADIAL_STEP_PX))
    cavity = outside = 0.0
    for _ in range(3):
        endo, epi = _runs_at(s, radii, 0.5 * (top + max(cavity, outside)), min_wall_px, max_gap_px)
        ok = np.isfinite(epi)
        if ok.sum() < 5:
            return None
        # Clipped: on noise a run can start past a ray's last sample, which would leave its wall
        # empty.
        a = np.minimum(np.searchsorted(radii, np.nan_to_num(endo)), n - 1)
        b = np.minimum(np.searchsorted(radii, np.nan_to_num(epi)), last)
        # A small cavity (apical slices) is sampled up to half its radius.
        cav = ok[:, None] & (idx[None, :] < np.minimum(a - off, a // 2)[:, None]) & inside
        lo_out = np.where(b + off + span <= last, b + off, last - span)
        out = (
            ok[:, None]
            & (idx[None, :] >= lo_out[:, None])
            & (idx[None, :] <= (lo_out + span)[:, None])
            & inside
        )
        outside = float(np.median(s[out])) if out.sum() >= 20 else 0.0
        has_cavity = cav.any(axis=1).sum() >= 0.25 * ok.sum() and cav.sum() >= 20
        cavity = float(np.median(s[cav])) if has_cavity else outside
        if not has_cavity:
            cav = np.zeros_like(cav)
        top = float(
            np.median([s[i, a[i]:max(b[i], a[i] + 1)].max() for i in np.flatnonzero(ok)])
        )
    return endo, epi, ok, (top, cavity, outside), (cav, out)


def _first_walls(sub, radii, endo, epi, levels, sig0, min_wall_px):
    """
    Place each ray's first wall edges from its half-excess width (step 3 of :func:`_wall_runs`).

    ``sub`` holds the rays with a run, ``levels`` the (cavity, outside) energies and ``sig0`` the
    blur, px; returns the (endo, epi) radii, px.
    """
    cavity, outside = levels
    n = sub.shape[1]
    a = np.minimum(np.searchsorted(radii, np.nan_to_num(endo)), n - 1)
    b = np.searchsorted(radii, epi)
    core = np.array(
        [ai + int(np.argmax(si[ai:max(bi, ai + 1)])) for si, ai, bi in zip(sub, a, b)]
    )
    pk = sub[np.arange(len(sub)), core]
    l, r = _crossings(
        sub, radii, core, cavity + 0.5 * (pk - cavity), outside + 0.5 * (pk - outside)
    )
    w_tab, half_tab = _half_width_table()
    w = np.interp((r - l) / sig0, half_tab, w_tab) * sig0
    rho = np.where(l <= 0.0, 0.5, _edge_fraction(w / sig0))  # from the ray origin: one edge only
    e, q = _crossings(
        sub, radii, core, cavity + rho * (pk - cavity), outside + rho * (pk - outside)
    )
    thin = (q - e) < np.maximum(min_wall_px, 0.5 * (r - l))
    return np.where(thin, l, e), np.where(thin, r, q)


def _crossings(s, radii, core, t_in, t_out):
    """
    Find where each ray's profile, followed from its ``core`` sample, falls to the levels, px.

    It falls to ``t_in`` inward and to ``t_out`` outward (linear interpolation). Inward: 0 when it
    never does (the wall starts at the ray origin); outward: the last radius. Both equal
    ``radii[core]`` when the core itself is not above the level.
    """
    k, n = s.shape
    rows = np.arange(k)
    idx = np.arange(n)[None, :]
    step = radii[1] - radii[0]
    t_in = np.broadcast_to(np.asarray(t_in, dtype=np.float64), (k,))
    t_out = np.broadcast_to(np.asarray(t_out, dtype=np.float64), (k,))
    below = (idx <= core[:, None]) & (s <= t_in[:, None])
    has = below.any(axis=1)
    jl = np.where(has, n - 1 - np.argmax(below[:, ::-1], axis=1), 0)
    jl1 = np.minimum(jl + 1, n - 1)
    den = s[rows, jl1] - s[rows, jl]
    frac = np.clip((t_in - s[rows, jl]) / np.where(den > 0, den, np.inf), 0.0, 1.0)
    left = np.where(has, radii[jl] + step * frac, 0.0)
    below = (idx >= core[:, None]) & (s <= t_out[:, None])
    has = below.any(axis=1)
    jr = np.where(has, np.argmax(below, axis=1), n - 1)
    jr0 = np.maximum(jr - 1, 0)
    den = s[rows, jr0] - s[rows, jr]
    frac = np.clip((s[rows, jr0] - t_out) / np.where(den > 0, den, np.inf), 0.0, 1.0)
    right = np.where(has, radii[jr0] + step * frac, radii[-1])
    dead = (s[rows, core] <= t_in) | (s[rows, core] <= t_out)
    left = np.where(dead, radii[core], left)
    right = np.where(dead, radii[core], np.maximum(right, left))
    return left, right


def _edge_fraction(u):
    """
    Fraction of a blurred wall's peak excess found at its edges, wall width ``u`` σ.

    A wall of width w under a Gaussian blur σ peaks at ``2Φ(w/2σ) − 1`` of its plateau and
    reads ``½ − Φ(−w/σ)`` of it at its edges: ½ of the peak for a thick wall, more for a thin one.
    """
    u = np.maximum(np.asarray(u, dtype=np.float64), 1e-6)
    return (0.5 - _phi(-u)) / (2.0 * _phi(0.5 * u) - 1.0)


@functools.lru_cache(maxsize=1)
def _half_width_table():
    """(w/σ, width at half peak/σ) of a Gaussian-blurred wall, both increasing (interpolation)."""
    u = np.concatenate([np.linspace(0.02, 2.0, 100), np.linspace(2.05, 60.0, 200)])
    x = np.linspace(0.0, 80.0, 16001)
    out = []
    for w in u:
        # The half level lies within w/2 + 1.2 (σ = 1): the profile up to w/2 + 4 finds the
        # same first sample at or below it as the whole grid (the whole grid only if not).
        m = int(np.searchsorted(x, 0.5 * w + 4.0)) + 1
        for xs in (x[:m], x):
            prof = _phi(xs + 0.5 * w) - _phi(xs - 0.5 * w)
            half = 0.5 * prof[0]
            below = prof <= half
            if below.any():
                break
        j = int(np.argmax(below))
        out.append(
            2.0 * (x[j - 1] + (x[j] - x[j - 1]) * (prof[j - 1] - half) / (prof[j - 1] - prof[j]))
        )
    return u, np.array(out)


def _phi(x):
    """Return the standard normal CDF."""
    return ndtr(x)


def _bent(r, sigma):
    """
    Return where a circular edge of radius ``r`` around the ray origin appears after a blur σ.

    Gaussian blur: its half level moves σ²/2r toward the centre of curvature (first order; r ≥ 2σ).
    """
    r = np.asarray(r, dtype=np.float64)
    with np.errstate(invalid='ignore'):
        return np.where(r > 0, r - sigma * sigma / (2.0 * np.maximum(np.abs(r), 2.0 * sigma)), r)


def _fit_walls(channels, radii, a0, b0, cav, out, min_wall_px, inside=None):
    """
    Least-squares walls [a, b] on several ray channels at once.

    Each channel ``(samples (K, R), blur σ, curvature σ, own outside)`` is modelled along a ray
    as its cavity level, a wall plateau and its outside level, the steps blurred by a Gaussian σ
    at the edges bent by :func:`_bent`: ``c + (P − c) Φ((r − a')/σ) + (o − P) Φ((r − b')/σ)``.
    The cavity level c is the channel's median over the ``cav`` samples (one blood pool); the
    outside level o the median over the ``out`` samples, or, for a channel flagged ``own
    outside``, each ray's own (:func:`_outside_per_ray`). The tag-free mean is flagged: around
    the LV it differs (the right ventricle's bright blood beside the septum, dark lung or tissue
    elsewhere), and one level for all rays pulled the septal epicardium into the RV pool and
    biased the common plateau, thickening every wall. The energy is not: the RV's blood is
    untagged, so its energy is the dark surroundings' (measured: per-ray energy levels too moved
    the normal preset's tagged surroundings, ES median 0.346 → 0.367 mm). The plateau P
    (linear least squares) and the noise variance (residuals) are common to all rays; each
    ray's a, b are the best of a grid of ±:data:`REFINE_REACH_PX` around the current ones
    (rays without a cavity keep a = −∞). :data:`REFINE_ITERATIONS` rounds.

    Returns
    -------
    endo, epi : ndarray, shape (K,)
        px (``endo = 0`` without a cavity).

    """
    k, n = channels[0][0].shape
    step = radii[1] - radii[0]
    nd = int(round(REFINE_REACH_PX / step))
    d = np.arange(-nd, nd + 1) * step
    chans = _channel_levels(channels, radii, b0, cav, out, inside)
    a = np.where(a0 > 0, a0, -np.inf)
    b = np.asarray(b0, dtype=np.float64).copy()
    span = 3.0 * max(ch['sig'] for ch in chans) + REFINE_REACH_PX
    for _ in range(REFINE_ITERATIONS):
        # Each ray's own window [a − span, b + span], gathered into a (K, L) block.
        start = np.clip(((np.maximum(a, 0.0) - span) / step).astype(int), 0, n - 1)
        stop = np.clip(((b + span) / step).astype(int) + 1, start + 1, n)
        length = int(np.max(stop - start))
        j = np.arange(length)[None, :]
        cols = start[:, None] + j
        win = (cols < stop[:, None]).astype(np.float64)
        cols = np.minimum(cols, n - 1)
        # Shifted profiles come from one evaluation on each window extended by the reach.
        r_ext = (start[:, None] + np.arange(-nd, length + nd)[None, :]) * step
        tot = 0.0
        for ch in chans:
            tot = tot + _shift_costs(ch, a, b, (cols, win, r_ext), nd, length)
        av = np.where(np.isfinite(a)[:, None], a[:, None] + d[None, :], -np.inf)
        bv = b[:, None] + d[None, :]
        tot = np.where(
            bv[:, None, :] - np.maximum(av, 0.0)[:, :, None] >= min_wall_px, tot, np.inf
        )
        a, b = _best_shift(tot, av, bv, d[1] - d[0], a, b)
    return np.maximum(a, 0.0), b


def _channel_levels(channels, radii, b0, cav, out, inside):
    """Each channel's cavity and outside levels (:func:`_fit_walls`), as one dict per channel."""
    k = channels[0][0].shape[0]
    chans = []
    for samples, sigma, curv, own_outside in channels:
        o = float(np.median(samples[out])) if out.sum() >= 20 else float(np.median(samples[:, -1]))
        c = float(np.median(samples[cav])) if cav.sum() >= 20 else o
        if own_outside:
            o = _outside_per_ray(samples, radii, b0, sigma, inside, o)
        else:
            o = np.full((k, 1), o)
        chans.append({'s': samples, 'sig': float(sigma), 'curv': float(curv), 'c': c, 'o': o})
    return chans


def _shift_costs(ch, a, b, window, nd, length):
    """
    One channel's misfit for every pair of edge shifts, over its noise variance, (K, D, D).

    ``window`` is ``(cols, win, r_ext)``: each ray's sample columns, its 1/0 window weights and
    the radii of the window extended by ``nd`` steps on both sides, px.
    """
    cols, win, r_ext = window
    sig, c, o = ch['sig'], ch['c'], ch['o']
    y = np.take_along_axis(ch['s'], cols, axis=1)
    fa = _phi((r_ext - _bent(a, ch['curv'])[:, None]) / sig)
    fb = _phi((r_ext - _bent(b, ch['curv'])[:, None]) / sig)
    pa, pb = fa[:, nd:nd + length], fb[:, nd:nd + length]
    g = (pa - pb) * win
    yy = (y - c * (1.0 - pa) - o * pb) * win
    p = float(np.sum(g * yy) / max(float(np.sum(g * g)), 1e-300))
    var = max(
        float(np.sum((yy - p * g) ** 2)) / max(float(win.sum()), 1.0),
        (1e-3 * max(abs(p - c), float(np.max(np.abs(p - o))), 1e-300)) ** 2,
    )
    # Window m of the extended grid holds the profile shifted by (nd − m) samples.
    sa = np.lib.stride_tricks.sliding_window_view(fa, length, axis=1)[:, ::-1]
    sb = np.lib.stride_tricks.sliding_window_view(fb, length, axis=1)[:, ::-1]
    # In place, in the same order of operations: no (K, D, L) temporaries.
    ya = (p - c) * sa
    np.subtract(y[:, None, :] - c, ya, out=ya)
    ya *= win[:, None, :]
    bb = (o - p)[:, :, None] * sb
    bb *= win[:, None, :]
    # Batched matmul (BLAS) for the cross term: ~3x faster than einsum, the same to a
    # few ulp (every mask and tag point of the default study unchanged).
    ss = (
        np.sum(ya * ya, axis=2)[:, :, None]
        - 2.0 * np.matmul(ya, bb.transpose(0, 2, 1))
        + np.sum(bb * bb, axis=2)[:, None, :]
    )
    return ss / var


def _best_shift(tot, av, bv, dstep, a, b):
    """Move each ray's edges to its least-cost shifts, to a sub-step by parabolas, (a, b) px."""
    k = tot.shape[0]
    rows = np.arange(k)
    flat = tot.reshape(k, -1)
    jm = np.argmin(flat, axis=1)
    fin = np.isfinite(flat[rows, jm])
    ia, ib = np.unravel_index(jm, tot.shape[1:])
    # Sub-step: a parabola through the minimum and its neighbours along each edge (the
    # walls then move continuously with the image).
    m = tot.shape[1] - 1
    fa_ = _parabola_offset(
        tot[rows, np.maximum(ia - 1, 0), ib],
        tot[rows, ia, ib],
        tot[rows, np.minimum(ia + 1, m), ib],
    )
    fb_ = _parabola_offset(
        tot[rows, ia, np.maximum(ib - 1, 0)],
        tot[rows, ia, ib],
        tot[rows, ia, np.minimum(ib + 1, m)],
    )
    fa_ = np.where((ia > 0) & (ia < m), fa_, 0.0)
    fb_ = np.where((ib > 0) & (ib < m), fb_, 0.0)
    a = np.where(fin, av[rows, ia] + fa_ * dstep, a)
    b = np.where(fin, bv[rows, ib] + fb_ * dstep, b)
    return a, b


def _outside_per_ray(samples, radii, epi, sigma, inside, fallback):
    """
    Each ray's outside level: the median of its samples just beyond its epicardium.

    Parameters
    ----------
    samples : ndarray, shape (K, R)
        One channel's ray samples.
    radii : ndarray, shape (R,)
        Sample radii, px.
    epi : ndarray, shape (K,)
        Current epicardial radius per ray, px.
    sigma : float
        The channel's edge blur, px: samples between :data:`OUTSIDE_NEAR_SIGMA` σ beyond ``epi``.
    inside : ndarray of bool, shape (K, R), or None
        Samples within the image (None: all).
    fallback : float
        The slice's outside level, kept on rays with fewer than 4 such samples (1 px).

    Returns
    -------
    ndarray, shape (K, 1)
        Outside level per ray (channel units).

    """
    lo, hi = OUTSIDE_NEAR_SIGMA
    r = radii[None, :]
    e = np.asarray(epi, dtype=np.float64)[:, None]
    near = (r >= e + lo * sigma) & (r <= e + hi * sigma)
    if inside is not None:
        near &= inside
    vals = np.where(near, samples, np.nan)
    enough = near.sum(axis=1) >= 4
    with np.errstate(all='ignore'):
        med = np.nanmedian(np.where(enough[:, None], vals, 0.0), axis=1)
    return np.where(enough, med, float(fallback))[:, None]


def _parabola_offset(ym, y0, yp):
    """
    Return the vertex offset of the parabola through (−1, ym), (0, y0), (1, yp), in [−½, ½].

    0 where the three are not convex or not finite.
    """
    with np.errstate(invalid='ignore', divide='ignore'):
        den = ym - 2.0 * y0 + yp
        off = np.where(np.isfinite(den) & (den > 0), 0.5 * (ym - yp) / den, 0.0)
    return np.clip(np.nan_to_num(off), -0.5, 0.5)


def _runs_at(s, radii, thr, min_wall_px, max_gap_px):
    """First run of ``s > thr`` per row of ray samples ``s`` (K, R); see :func:`_ray_runs`."""
    inside = s > thr
    k, n = inside.shape
    step = radii[1] - radii[0]
    # Close short gaps: a pixel is "in" if an "in" sample lies within max_gap/2 on both sides.
    g = max(int(round(max_gap_px / step)), 1)
    closed = ndi.binary_closing(inside, structure=np.ones((1, g + 1), bool)) | inside
    closed[:, :g] |= inside[:, :g]
    endo = np.full(k, np.nan)
    epi = np.full(k, np.nan)
    min_len = int(np.ceil(min_wall_px / step))
    padded = np.concatenate([np.zeros((k, 1), bool), closed, np.zeros((k, 1), bool)], 1)
    d = np.diff(padded.astype(np.int8), axis=1)
    # Runs in row-major order: the i-th start and the i-th end bound one run (padded rows).
    row, a = np.nonzero(d == 1)
    b = np.nonzero(d == -1)[1]
    good = (b - a) >= min_len
    rows, first = np.unique(row[good], return_index=True)
    if rows.size == 0:
        return endo, epi
    a, b = a[good][first], b[good][first]  # each ray's first long run covers samples [a, b)
    a1, b1 = np.maximum(a - 1, 0), np.minimum(b, n - 1)
    sa0, sa1 = s[rows, a1], s[rows, np.minimum(a, n - 1)]
    sb0, sb1 = s[rows, b - 1], s[rows, b1]
    with np.errstate(invalid='ignore', divide='ignore'):
        e = radii[a1] + step * (thr - sa0) / np.maximum(sa1 - sa0, 1e-300)
        q = radii[b - 1] + step * (sb0 - thr) / np.maximum(sb0 - sb1, 1e-300)
    endo[rows] = np.where(a == 0, 0.0, e)
    epi[rows] = np.where(b >= n, radii[-1], q)
    return endo, epi


def _circular_smooth(
    r: np.ndarray, sigma_rays: float, median: int = 5, closed: bool = True
) -> np.ndarray:
    """Median then Gaussian smoothing of a radius profile over rays (the shape prior)."""
    mode = 'wrap' if closed else 'nearest'
    out = ndi.median_filter(r, size=median, mode=mode)
    return ndi.gaussian_filter1d(out, sigma_rays, mode=mode)


def _robust_fill(r: np.ndarray) -> np.ndarray:
    """Fill NaN rays of a closed profile by periodic linear interpolation."""
    ok = np.isfinite(r)
    if ok.all():
        return r
    idx = np.arange(r.size)
    return np.interp(idx, idx[ok], r[ok], period=r.size)


def polar_mask(
    shape: tuple[int, int],
    centre_rc: np.ndarray,
    angles: np.ndarray,
    endo: np.ndarray,
    epi: np.ndarray,
    axis_rc: np.ndarray | None = None,
    base_level: float = np.inf,
) -> np.ndarray:
    """
    Rasterise the polar myocardium ``endo(θ) ≤ ρ ≤ epi(θ)`` (pixel centres).

    Optionally cut at ``(x − centre)·axis_rc ≤ base_level`` (LA base). NaN rays are outside.

    Returns
    -------
    ndarray of bool, shape ``shape``

    """
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]]
    dr, dc = rr - centre_rc[0], cc - centre_rc[1]
    rho = np.hypot(dr, dc)
    th = np.arctan2(dr, dc)
    step = angles[1] - angles[0]
    # Nearest-two-ray linear interpolation on the periodic grid.
    f = (th - angles[0]) / step % angles.size
    i0 = np.floor(f).astype(int) % angles.size
    i1 = (i0 + 1) % angles.size
    t = f - np.floor(f)
    lo = (1 - t) * endo[i0] + t * endo[i1]
    hi = (1 - t) * epi[i0] + t * epi[i1]
    with np.errstate(invalid='ignore'):
        m = (rho >= lo) & (rho <= hi)
    if axis_rc is not None and np.isfinite(base_level):
        m &= below_base(shape, centre_rc, axis_rc, base_level)
    return m


def below_base(shape: tuple[int, int], centre_rc, axis_rc, base_level: float) -> np.ndarray:
    """
    Return the pixels on the apical side of an LA base cut, shape ``shape``.

    Those whose centre ``x`` has ``(x − centre_rc)·axis_rc ≤ base_level`` (px along the unit
    in-plane axis ``axis_rc``, apex → base, from ``centre_rc``, (row, col)).
    """
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]]
    return (rr - centre_rc[0]) * axis_rc[0] + (cc - centre_rc[1]) * axis_rc[1] <= base_level


# --------------------------------------------------------------------------- slices
def _fail(shape, reason: str, view: str) -> SliceSegmentation:
    return SliceSegmentation(False, reason, np.zeros(shape, bool), view=view)


def _checked_image(image, view: str):
    """``(float image, None)`` for a usable slice, else ``(None, failed SliceSegmentation)``."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 16 or not np.all(np.isfinite(img)):
        return None, _fail(
            np.shape(img)[:2] if img.ndim >= 2 else (0, 0),
            'image must be a finite 2-D array of at least 16x16 pixels',
            view,
        )
    if float(img.std()) == 0.0:
        return None, _fail(img.shape, 'image is constant (no signal)', view)
    return img, None


def segment_sa(
    image: np.ndarray,
    centre_rc,
    pixel_spacing_mm: float,
    *,
    max_radius_mm: float = 60.0,
    min_wall_mm: float = 2.0,
    max_invalid_fraction: float = 0.25,
    features: TagFeatures | None = None,
    families: int = 2,
) -> SliceSegmentation:
    """
    Segment the myocardium of one ED short-axis tagged image.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        ED tagged image (any intensity unit).
    centre_rc : array_like, shape (2,)
        Long-axis intersection with the slice, (row, col) px: inside (or near) the blood pool.
    pixel_spacing_mm : float
        Isotropic in-plane spacing, mm.
    max_radius_mm : float
        Longest ray, mm (larger than any epicardial radius).
    min_wall_mm : float
        Shortest myocardial run accepted on a ray, mm.
    max_invalid_fraction : float
        Reject the slice when more rays than this find no myocardium.
    features : TagFeatures or list of TagFeatures, optional
        Precomputed :func:`tag_features` (only that estimate is tried) or
        :func:`candidate_features` (each tried, the better kept, as by default).
    families : int
        Tag directions in the image when ``features`` are not given: 2 for a grid, 1 for one
        family of tag lines (``Frame.tag_lines`` ``TAGS_LINES``; :func:`candidate_features`).

    Returns
    -------
    SliceSegmentation
        ``ok=False`` with a reason when the slice holds no recognisable annulus (no tags, no
        tagged ring around the centre, implausible wall).

    """
    img, failed = _checked_image(image, 'SA')
    if failed is not None:
        return failed
    c = np.asarray(centre_rc, dtype=np.float64)
    return _segment_candidates(
        img,
        features,
        c,
        pixel_spacing_mm,
        max_radius_mm,
        min_wall_mm,
        'SA',
        families,
        lambda angles, endo, epi, feat: _sa_from_runs(
            img.shape,
            c,
            angles,
            endo,
            epi,
            pixel_spacing_mm,
            max_radius_mm,
            min_wall_mm,
            max_invalid_fraction,
        ),
    )


def _segment_candidates(
    img, features, c, pixel_spacing_mm, max_radius_mm, min_wall_mm, view, families, finish
):
    """
    Find the wall runs around ``c`` under each of :func:`candidate_features` and keep the best.

    Under the given ``features`` instead when passed (``families``: tag directions, 2 or 1, of
    the estimated ones); runs are shaped by
    ``finish(angles, endo, epi, features)``; the best by :func:`_best_of`.
    """
    feats = (
        candidate_features(img, pixel_spacing_mm, families)
        if features is None
        else [features]
        if isinstance(features, TagFeatures)
        else list(features)
    )
    angles = np.linspace(-np.pi, np.pi, NUM_RAYS, endpoint=False)
    results = []
    for feat in feats:
        endo, epi, lv = _wall_runs(
            feat,
            c,
            angles,
            max_radius_mm / pixel_spacing_mm,
            min_wall_mm / pixel_spacing_mm,
            1.0 / pixel_spacing_mm,
        )
        if lv is None:
            results.append(
                (
                    _fail(
                        img.shape, 'no tagged tissue around the long axis (tag energy flat)', view
                    ),
                    -np.inf,
                )
            )
        else:
            results.append((finish(angles, endo, epi, feat), _wall_cnr(lv, feat)))
    return _best_of(results)


def _sa_from_runs(
    shape, c, angles, endo, epi, pixel_spacing_mm, max_radius_mm, min_wall_mm, max_invalid_fraction
):
    """Check, smooth over angle and rasterise the SA rays' wall runs."""
    rmax = max_radius_mm / pixel_spacing_mm
    bad = ~np.isfinite(epi)
    if bad.mean() > max_invalid_fraction:
        return _fail(
            shape,
            f'no myocardial annulus: {100 * bad.mean():.0f}% of rays from the long axis '
            f'find no tagged wall within {max_radius_mm:g} mm',
            'SA',
        )
    if np.mean(epi[~bad] >= rmax - 1) > 0.1:
        return _fail(
            shape,
            f'tagged region extends beyond {max_radius_mm:g} mm from the long axis '
            '(no closed epicardium)',
            'SA',
        )
    endo_s = _circular_smooth(_robust_fill(endo), 2.0)
    epi_s = _circular_smooth(_robust_fill(epi), 2.0)
    endo_s = np.clip(endo_s, 0.0, None)
    wall = (epi_s - endo_s) * pixel_spacing_mm
    if np.median(wall) < min_wall_mm or np.median(wall) > 35.0:
        return _fail(shape, f'implausible wall thickness {np.median(wall):.1f} mm', 'SA')
    epi_s = np.maximum(epi_s, endo_s + 0.5)
    mask = polar_mask(shape, c, angles, endo_s, epi_s)
    return SliceSegmentation(True, '', mask, c, angles, endo_s, epi_s, view='SA')


def segment_la(
    image: np.ndarray,
    centre_rc,
    axis_rc,
    pixel_spacing_mm: float,
    *,
    max_radius_mm: float = 80.0,
    min_wall_mm: float = 2.0,
    min_arc_deg: float = 150.0,
    features: TagFeatures | None = None,
    families: int = 2,
) -> SliceSegmentation:
    """
    Segment the horseshoe myocardium of one ED long-axis tagged image.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
        Tagged ED long-axis image (intensity, any scale).
    centre_rc : array_like, shape (2,)
        A point of the long axis inside the cavity (e.g. mid SA stack), (row, col) px.
    axis_rc : array_like, shape (2,)
        In-plane long-axis direction apex → base, (row, col) (normalised here).
    pixel_spacing_mm : float
        In-plane pixel size, mm.
    max_radius_mm : float
        Longest ray, mm (must reach the apex from ``centre_rc``).
    min_wall_mm : float
        Shortest myocardial run accepted on a ray, mm (as :func:`segment_sa`).
    min_arc_deg : float
        Reject when the contiguous arc of rays that meet myocardium is shorter than this.
    features : TagFeatures, optional
        As :func:`segment_sa`.
    families : int
        As :func:`segment_sa`.

    Returns
    -------
    SliceSegmentation
        With ``base_level`` (px along ``axis_rc`` from the centre) where the horseshoe is cut.

    """
    img, failed = _checked_image(image, 'LA')
    if failed is not None:
        return failed
    c = np.asarray(centre_rc, dtype=np.float64)
    ax = np.asarray(axis_rc, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)
    rmax = max_radius_mm / pixel_spacing_mm
    return _segment_candidates(
        img,
        features,
        c,
        pixel_spacing_mm,
        max_radius_mm,
        min_wall_mm,
        'LA',
        families,
        lambda angles, endo, epi, feat: _la_from_runs(
            img.shape,
            c,
            ax,
            angles,
            endo,
            epi,
            rmax,
            min_arc_deg,
            _mid_wall_energy(feat, c, angles, endo, epi),
        ),
    )


def _enclosed_gaps(valid: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """
    Gaps between valid rays that lie wholly among ``allowed`` rays.

    Parameters
    ----------
    valid, allowed : ndarray of bool, shape (K,)
        Per ray, circular.

    Returns
    -------
    ndarray of bool, shape (K,)
        The rays of every circular run of ``~valid`` that is all ``allowed``.

    """
    out = np.zeros(valid.size, bool)
    if not valid.any():
        return out
    start = int(np.flatnonzero(valid)[0])
    v, a = np.roll(valid, -start), np.roll(allowed, -start)
    d = np.diff(np.concatenate([[0], (~v).astype(np.int8), [0]]))
    for s0, e0 in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        if a[s0:e0].all():
            out[s0:e0] = True
    return np.roll(out, start)


def _level_ends(arc, valid, endo, epi, angles, ax, base_dir):
    """
    Carry the lower end of the horseshoe across gaps up to the level of the other end.

    The LA plane contains the long axis and the base plane is perpendicular to it, so the
    two ends of the horseshoe lie at one level along the axis. When one end stops more than a
    wall thickness below the other, its side wall was lost over a stretch (too faint for the
    energy; the wall around the cavity is one cup, so rays between the cup's rim and the apex
    all meet it): the next stretch of wall beyond that gap, on the same side of the base
    direction, continues the horseshoe as long as it does not rise more than a wall thickness
    above the other end (beyond the base lie the atrium's edges, not the LV wall). Gaps
    crossed are filled by linear interpolation of the radii. A wall thickness (median over the
    arc) is the tolerance: an end stops where the blurred wall's run fades under the threshold,
    within about a wall's width of the base, and an axis estimated a few degrees off tilts
    the two ends by less across the cavity. Both ends low (both sides lost) is left as it is.

    Parameters
    ----------
    arc : ndarray of int
        Rays of the horseshoe in increasing circular order.
    valid : ndarray of bool, shape (K,)
        Whether each ray met myocardium.
    endo, epi : ndarray, shape (K,)
        Inner and outer wall radius along each ray, px.
    angles : ndarray, shape (K,)
        Ray angles, rad.
    ax : ndarray, shape (2,)
        Unit axis direction apex → base, (row, col).
    base_dir : float
        Its angle, rad.

    Returns
    -------
    arc, endo, epi

    """
    k = valid.size
    phi = (angles - base_dir + np.pi) % (2.0 * np.pi) - np.pi  # 0: toward the base
    endo, epi = endo.copy(), epi.copy()
    arc = [int(i) for i in arc]

    def level(i):
        return 0.5 * (max(endo[i], 0.0) + epi[i]) * np.cos(phi[i])

    while len(arc) < k:
        tol = float(np.median(epi[arc] - np.maximum(endo[arc], 0.0)))
        za, zb = level(arc[0]), level(arc[-1])
        if abs(za - zb) <= tol:
            break
        end, step = (arc[0], -1) if za < zb else (arc[-1], 1)
        side = np.sign(phi[end])
        gap, i = [], (end + step) % k
        while not valid[i] and np.sign(phi[i]) == side and len(gap) < k:
            gap.append(i)
            i = (i + step) % k
        stretch = []
        while valid[i] and np.sign(phi[i]) == side and i not in arc:
            stretch.append(i)
            i = (i + step) % k
        if not gap or not stretch or level(stretch[-1]) > max(za, zb) + tol:
            break
        for n, g in enumerate(gap, 1):
            w = n / (len(gap) + 1.0)
            endo[g] = (1.0 - w) * endo[end] + w * endo[stretch[0]]
            epi[g] = (1.0 - w) * epi[end] + w * epi[stretch[0]]
        arc = arc + gap + stretch if step > 0 else stretch[::-1] + gap[::-1] + arc
    return np.array(arc), endo, epi


def _longest_run(v: np.ndarray) -> int:
    """Return the length of the longest run of True in a boolean sequence."""
    d = np.diff(np.concatenate([[0], np.asarray(v, np.int8), [0]]))
    return int(np.max(np.flatnonzero(d == -1) - np.flatnonzero(d == 1), initial=0))


def _thin_ends_cut(arc, found, endo, epi, angles, base_dir, strength=None):
    """
    End each side of the horseshoe where the ventricular wall ends, not on the atrium's edge.

    Past the base the rays toward the atrium can still meet runs: the edge of the untagged
    atrial blood against the dark or differently tagged surroundings leaves a thin residue in the
    tag energy (a step, not a tagged wall), and the runs continue up the atrium's side and
    across its roof (measured on a dilated LV with bright blood and dark surroundings: runs 2–5
    mm thick up to 26 mm above the base, the wall 7–10 mm; the horseshoe and the base then
    reached the atrium's roof; their tag energy 0.02–0.08 against the wall's 0.06–0.18).
    Walking from the horseshoe's middle (the apex) toward each end,
    over the rays that point basally of the axis point, the wall ends before the first
    :data:`LA_THIN_END_RAYS` consecutive rays that are each thinner than
    :data:`LA_THIN_END_FRACTION` of the horseshoe's own median wall thickness or met nothing,
    at least one of them a thin run (a stretch that met nothing is a gap in a faint wall, which
    the callers bridge, not an end), and beyond which no stretch of twice as many consecutive
    rays meets a full wall (a weak stretch within a thin wall is followed by more wall; past the
    base only the atrium's corners, a few rays). The end is the last ray before them that met a
    full wall.
    Every constant is relative to the slice's own wall and ray spacing.

    Parameters
    ----------
    arc : ndarray of int
        Rays of the horseshoe in increasing circular order.
    found : ndarray of bool, shape (K,)
        Whether each ray's own run met a wall (before gaps were bridged).
    endo, epi : ndarray, shape (K,)
        Inner and outer wall radius along each ray, px.
    angles : ndarray, shape (K,)
        Ray angles, rad.
    base_dir : float
        Angle of the in-plane axis direction apex → base, rad.
    strength : ndarray, shape (K,), optional
        Tag energy at each ray's mid-wall point (:func:`_mid_wall_energy`); a ray below
        :data:`LA_THIN_END_FRACTION` of the horseshoe's median counts as thin too (the atrium's
        edge is a step's residue, weaker than the tagged wall).

    Returns
    -------
    ndarray of int
        The horseshoe's rays, each side ended where its wall ends.

    """
    arc = np.asarray(arc)
    wall = epi - np.maximum(endo, 0.0)
    own = found[arc]
    if own.sum() < 2 * LA_THIN_END_RAYS:
        return arc
    thin = wall < LA_THIN_END_FRACTION * float(np.median(wall[arc][own]))
    if strength is not None:
        e = np.asarray(strength, float)
        ok = own & np.isfinite(e[arc])
        if ok.any():
            with np.errstate(invalid='ignore'):
                thin |= e < LA_THIN_END_FRACTION * float(np.median(e[arc][ok]))
    basal = np.cos(angles - base_dir) > 0
    mid = arc.size // 2
    lo, hi = 0, arc.size - 1
    for side in (-1, 1):
        order = np.arange(mid, -1, -1) if side < 0 else np.arange(mid, arc.size)
        rays = arc[order]
        weak = ~found[rays] | thin[rays]
        for j in range(len(rays) - LA_THIN_END_RAYS + 1):
            win = rays[j:j + LA_THIN_END_RAYS]
            if not (basal[win].all() and weak[j:j + LA_THIN_END_RAYS].all()):
                continue
            if not (found[win] & thin[win]).any():
                continue
            if _longest_run(~weak[j:]) >= 2 * LA_THIN_END_RAYS:  # more wall beyond
                continue
            full = np.flatnonzero(found[rays[:j]] & ~thin[rays[:j]])
            if full.size:
                end = int(order[full[-1]])
                lo, hi = (end, hi) if side < 0 else (lo, end)
            break
    return arc[lo:hi + 1]


def _mid_wall_energy(feat: TagFeatures, c, angles, endo, epi) -> np.ndarray:
    """
    Return the tag energy at each ray's mid-wall point (NaN where the ray met no wall).

    Parameters
    ----------
    feat : TagFeatures
        The features the runs were found in.
    c : ndarray, shape (2,)
        Ray origin, (row, col) px.
    angles : ndarray, shape (K,)
        Ray angles, rad.
    endo, epi : ndarray, shape (K,)
        Inner and outer wall radius along each ray, px (NaN: no wall).

    Returns
    -------
    ndarray, shape (K,)
        Energy, image intensity units.

    """
    mid = 0.5 * (np.maximum(np.nan_to_num(endo), 0.0) + np.nan_to_num(epi))
    rc = c[None] + mid[:, None] * np.stack([np.sin(angles), np.cos(angles)], 1)
    e = ndi.map_coordinates(np.asarray(feat.energy, float), rc.T, order=1, mode='nearest')
    return np.where(np.isfinite(epi), e, np.nan)


def _la_from_runs(shape, c, ax, angles, endo, epi, rmax, min_arc_deg, strength=None):
    """
    Horseshoe arc, base cut and rasterisation of the LA rays' wall runs.

    The horseshoe is the arc of rays that meet the wall, the atrium's opening the rest. A
    stretch of wall the runs miss (where the surroundings are tagged, the wall's tag energy
    stands only a little above theirs, and a side wall can fall under the detection threshold
    over tens of degrees) would otherwise end the arc there, and the base be cut that much too
    low: gaps that cannot be the opening are bridged (rays pointing apically of the axis point;
    :func:`_level_ends` for the side walls).
    """
    valid = np.isfinite(epi) & (epi < rmax - 1)
    found = valid.copy()  # the rays whose own run met a wall (before any bridging)
    base_dir = np.arctan2(ax[0], ax[1])
    valid, met, endo, epi = _bridged(valid, endo, epi, angles, base_dir)
    # The horseshoe is the longest circular run of valid rays; it must not include the base
    # direction (the atrium side is open).
    if valid.all() or not valid.any():
        return _fail(
            shape,
            'no horseshoe: the myocardium found is '
            + ('closed around the axis point' if valid.any() else 'absent'),
            'LA',
        )
    arc = _longest_circular_run(valid)
    if np.cos(angles[arc[arc.size // 2]] - base_dir) < 0:
        arc, endo, epi = _level_ends(arc, valid, endo, epi, angles, ax, base_dir)
        arc = _thin_ends_cut(arc, found, endo, epi, angles, base_dir, strength)
    # The long axis runs through the mitral opening, so the LV's horseshoe never holds the ray
    # toward the base: one that does has closed over the atrium (the edges of its blood taken
    # for wall), and its ends say nothing of where the base is.
    toward_base = np.abs((angles[arc] - base_dir + np.pi) % (2.0 * np.pi) - np.pi)
    base_found = not bool(np.any(toward_base <= 0.5 * (angles[1] - angles[0])))
    # Only rays that met the wall count toward the arc (not the wide gaps bridged above).
    arc_deg = np.count_nonzero(met[arc]) * 360.0 / NUM_RAYS
    if arc_deg < min_arc_deg:
        return _fail(shape, f'horseshoe arc only {arc_deg:.0f} deg (< {min_arc_deg:g})', 'LA')
    mid_arc = angles[arc[arc.size // 2]]
    if np.cos(mid_arc - base_dir) > 0:
        return _fail(
            shape, 'horseshoe opens toward the apex (long-axis orientation inconsistent)', 'LA'
        )
    return _horseshoe_mask(shape, c, ax, angles, arc, endo, epi, base_found)


def _bridged(valid, endo, epi, angles, base_dir):
    """
    Bridge the gaps in the LA rays' runs that cannot be the atrium's opening.

    Returns ``(valid, met, endo, epi)``: ``met`` counts only narrow gaps as wall (the wide
    apical ones bridged in ``valid`` are not), bridged radii interpolated, px.
    """
    # Bridge gaps of a few rays (noise, a wall locally thinner than the smallest run): the
    # atrium's opening is tens of degrees wide.
    gap = int(round(LA_MAX_GAP_DEG * NUM_RAYS / 360.0))
    met = valid
    if valid.any() and not valid.all():
        closed = ndi.binary_closing(np.concatenate([valid] * 3), structure=np.ones(gap + 1, bool))[
            NUM_RAYS:2 * NUM_RAYS
        ]
        met = closed.copy()
        # Gaps of any width among the rays that point apically of the axis point: the point
        # lies in the cavity, below the base plane, so those rays never reach the opening and
        # each meets the wall.
        closed |= _enclosed_gaps(valid, np.cos(angles - base_dir) < 0)
        fill = closed & ~valid
        if fill.any():
            endo, epi = endo.copy(), epi.copy()
            idx = np.arange(NUM_RAYS)
            for r in (endo, epi):
                r[fill] = np.interp(idx[fill], idx[valid], r[valid], period=NUM_RAYS)
            valid = closed
    return valid, met, endo, epi


def _longest_circular_run(valid: np.ndarray) -> np.ndarray:
    """Ray indices of the longest circular run of ``valid`` (not all True), in order."""
    start = int(np.flatnonzero(~valid)[0])
    rolled = np.roll(valid, -start)
    pad = np.concatenate([[False], rolled, [False]]).astype(np.int8)
    d = np.diff(pad)
    s_idx, e_idx = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    j = int(np.argmax(e_idx - s_idx))
    return (np.arange(s_idx[j], e_idx[j]) + start) % NUM_RAYS


def _horseshoe_mask(shape, c, ax, angles, arc, endo, epi, base_found=True) -> SliceSegmentation:
    """
    Smooth the arc's walls, cut them at the base level and rasterise the LA mask.

    Without ``base_found`` (a horseshoe closed over the atrium) the base level is NaN and the
    mask is not cut: the caller cuts it where the other views put the base.
    """
    e_arc = _circular_smooth(endo[arc], 1.5, median=5, closed=False)
    p_arc = _circular_smooth(epi[arc], 1.5, median=5, closed=False)
    # Base level: mid-wall axial coordinate of the two arc ends (each end ray stops at the
    # base plane, where the wall leaves the image plane's myocardium). The wall ends somewhere
    # between the last ray that meets it and the next: half a ray spacing beyond the last.
    ends = []
    half_step = 0.5 * (angles[1] - angles[0])
    for k, side in ((0, -1.0), (arc.size - 1, 1.0)):
        th = angles[arc[k]] + side * half_step
        rmid = 0.5 * (e_arc[k] + p_arc[k])
        ends.append(rmid * (np.sin(th) * ax[0] + np.cos(th) * ax[1]))
    base_level = float(np.mean(ends)) if base_found else float('nan')
    endo_full = np.full(NUM_RAYS, np.nan)
    epi_full = np.full(NUM_RAYS, np.nan)
    endo_full[arc] = np.clip(e_arc, 0.0, None)
    epi_full[arc] = np.maximum(p_arc, endo_full[arc] + 0.5)
    # Hold the end radii 12° beyond each end so the flat base cut, not the last ray, bounds
    # the mask there.
    ext = int(round(12.0 * NUM_RAYS / 360.0))
    for k in range(1, ext + 1):
        for src, dst in ((arc[0], (arc[0] - k) % NUM_RAYS), (arc[-1], (arc[-1] + k) % NUM_RAYS)):
            if not np.isfinite(epi_full[dst]):
                endo_full[dst], epi_full[dst] = endo_full[src], epi_full[src]
    mask = polar_mask(shape, c, angles, endo_full, epi_full, ax, base_level)
    return SliceSegmentation(
        True,
        '',
        mask,
        c,
        angles,
        endo_full,
        epi_full,
        view='LA',
        base_level=base_level,
        axis_rc=ax,
    )


def segment_from_mask(
    mask: np.ndarray,
    centre_rc,
    pixel_spacing_mm: float,
    axis_rc=None,
    max_radius_mm: float | None = None,
) -> SliceSegmentation:
    """
    Polar contours of a given myocardium mask (user labels), with the same ray machinery.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
        Myocardium mask of the slice (True = myocardium).
    centre_rc : array_like, shape (2,)
        Long-axis point in the slice, (row, col) px.
    pixel_spacing_mm : float
        In-plane pixel size, mm.
    axis_rc : array_like, shape (2,), optional
        LA only: in-plane axis direction apex → base; None for SA.
    max_radius_mm : float, optional
        Longest ray (default 60 mm SA, 80 mm LA).

    Returns
    -------
    SliceSegmentation
        ``mask`` is the input mask; contours from the 0.5 level of the mask lightly smoothed.

    """
    m = np.asarray(mask, bool)
    score = ndi.gaussian_filter(m.astype(np.float64), 0.7)
    c = np.asarray(centre_rc, dtype=np.float64)
    rmax_mm = max_radius_mm or (60.0 if axis_rc is None else 80.0)
    angles = np.linspace(-np.pi, np.pi, NUM_RAYS, endpoint=False)
    endo, epi = _ray_runs(
        score,
        c,
        angles,
        rmax_mm / pixel_spacing_mm,
        1.0 / pixel_spacing_mm,
        1.0 / pixel_spacing_mm,
    )
    if axis_rc is None:
        out = _sa_from_runs(m.shape, c, angles, endo, epi, pixel_spacing_mm, rmax_mm, 1.0, 0.25)
    else:
        ax = np.asarray(axis_rc, dtype=np.float64)
        out = _la_from_runs(
            m.shape,
            c,
            ax / np.linalg.norm(ax),
            angles,
            endo,
            epi,
            rmax_mm / pixel_spacing_mm,
            150.0,
        )
    if out.ok:
        out.mask = m
    out.source = 'mask'
    return out


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice overlap of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    s = a.sum() + b.sum()
    return 1.0 if s == 0 else float(2.0 * np.logical_and(a, b).sum() / s)

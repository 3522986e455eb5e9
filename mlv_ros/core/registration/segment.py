"""Automatic end-diastolic LV myocardium segmentation on tagged SA and LA images.

Why tag energy: SPAMM tags are laid down at end-diastole in all tissue, but flowing blood carries
them out of the slice within tens of milliseconds, so at ED the myocardium is *tagged and
bright*, the blood pool is *untagged*, and static background is tagged but dimmer. Two local
features separate the three classes (pixel units throughout):

* ``energy`` E — summed magnitude of the complex Gabor (demodulated band-pass) responses at the
  two tag wave vectors found in the spectrum; the envelope σ = λ/2 suppresses the tag
  harmonics and cross terms by ≈ e^{-2π²σ²/λ²} ≈ 0.7 %, so E is the local tag amplitude;
* ``mean`` M — the intensity smoothed with the same Gaussian, i.e. the tag-free local mean.

Both are linear in the tissue fractions of a pixel, so the 50 % crossing between two class
levels sits on the partial-volume boundary (fraction 0.5, the ground-truth convention).

Shape prior (paper §3.2 relies on a segmentation of both views; we use a geometric prior
instead of the paper's learned one):

* SA — a star-shaped annulus around the blood pool found at the long axis: rays from the axis
  point, one myocardial run per ray (endo = blood→myocardium crossing, epi =
  myocardium→background crossing), radii smoothed over angle.
* LA — the horseshoe: rays from a point on the long axis inside the cavity; rays toward the base
  find no myocardium (atrium), the contiguous arc that does is the horseshoe, cut flat at the
  base level perpendicular to the axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

#: Rays per slice (2° apart).
NUM_RAYS = 180
#: Radial sampling step along a ray, px.
RADIAL_STEP_PX = 0.25


@dataclass
class TagFeatures:
    """Tag-energy features of one image (see module docstring).

    Attributes
    ----------
    energy : ndarray, shape (rows, cols)
        Local tag amplitude E (image intensity units).
    mean : ndarray, shape (rows, cols)
        Tag-free local mean intensity M.
    wavelength_px : float
        Tag period λ of the strongest direction, px.
    wavevectors : ndarray, shape (2, 2)
        (row, col) spatial frequencies of the two tag directions, cycles / px.
    """

    energy: np.ndarray
    mean: np.ndarray
    wavelength_px: float
    wavevectors: np.ndarray


@dataclass
class SliceSegmentation:
    """Myocardium of one slice, in polar form around ``centre_rc`` plus the pixel mask.

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
        LA only: base-plane cut as a coordinate along ``axis_rc`` from ``centre_rc``, px.
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
    view: str = "SA"
    base_level: float = np.inf
    axis_rc: np.ndarray = field(default_factory=lambda: np.zeros(2))
    source: str = "auto"


# --------------------------------------------------------------------------- features
def tag_wavevectors(image: np.ndarray, min_period_px: float = 2.5,
                    max_period_px: float = 30.0) -> np.ndarray:
    """The two dominant tag wave vectors from the windowed magnitude spectrum.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
    min_period_px, max_period_px : float
        Search band of tag periods, px.

    Returns
    -------
    ndarray, shape (2, 2)
        (row, col) frequencies in cycles / px; the second direction is ≥ 30° from the first.
        Peaks are refined to sub-bin precision by parabolic interpolation.
    """
    img = np.asarray(image, dtype=np.float64)
    a = (img - img.mean()) * np.outer(np.hanning(img.shape[0]), np.hanning(img.shape[1]))
    spec = np.abs(np.fft.fft2(a))
    fy = np.fft.fftfreq(img.shape[0])
    fx = np.fft.fftfreq(img.shape[1])
    FY, FX = np.meshgrid(fy, fx, indexing="ij")
    fr = np.hypot(FY, FX)
    band = (fr >= 1.0 / max_period_px) & (fr <= 1.0 / min_period_px)
    s1 = np.where(band, spec, 0.0)
    i = np.unravel_index(int(np.argmax(s1)), s1.shape)
    k1 = np.array([FY[i], FX[i]])
    cosang = np.abs(FY * k1[0] + FX * k1[1]) / (fr * np.linalg.norm(k1) + 1e-12)
    s2 = np.where(cosang < np.cos(np.radians(30.0)), s1, 0.0)
    j = np.unravel_index(int(np.argmax(s2)), s2.shape)
    out = []
    for idx in (i, j):
        k = np.array([FY[idx], FX[idx]], dtype=np.float64)
        for ax, n in enumerate(img.shape):  # parabolic refinement per axis
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


def tag_features(image: np.ndarray, wavevectors: np.ndarray | None = None) -> TagFeatures:
    """Tag energy and tag-free mean of an image (module docstring).

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
    wavevectors : ndarray, shape (2, 2), optional
        (row, col) tag frequencies, cycles / px; estimated from the spectrum by default.

    Returns
    -------
    TagFeatures
    """
    img = np.asarray(image, dtype=np.float64)
    kv = tag_wavevectors(img) if wavevectors is None else np.asarray(wavevectors, dtype=np.float64)
    lam = 1.0 / float(np.linalg.norm(kv[0]))
    sigma = 0.5 * lam
    rr, cc = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    energy = np.zeros_like(img)
    for k in kv:
        z = img * np.exp(-2j * np.pi * (k[0] * rr + k[1] * cc))
        energy += np.hypot(ndi.gaussian_filter(z.real, sigma), ndi.gaussian_filter(z.imag, sigma))
    return TagFeatures(energy, ndi.gaussian_filter(img, sigma), lam, kv)


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


@dataclass
class _Levels:
    e_myo: float
    m_myo: float
    e_blood: float
    m_blood: float
    e_bg: float
    m_bg: float
    has_blood: bool


def _levels_around(img, centre_rc, radius_px: float, features=None):
    """Tag features of ``img`` and the tissue class levels within ``radius_px`` of the long-axis
    point ``centre_rc`` (None when the tag energy there is flat)."""
    feat = features or tag_features(img)
    rr, cc = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    return feat, _class_levels(feat, np.hypot(rr - centre_rc[0], cc - centre_rc[1]) < radius_px)


def _class_levels(feat: TagFeatures, region: np.ndarray) -> _Levels | None:
    """Class levels of myocardium / blood / background inside ``region`` (bool mask).

    Myocardium is the high class of an Otsu split of E; blood is untagged (E < ¼ E_myo) and
    brighter than the myocardial mean; background is the rest. None when the region holds no
    tagged tissue at all.
    """
    e, m = feat.energy[region], feat.mean[region]
    if e.size < 50 or not np.all(np.isfinite(e)):
        return None
    thr = _otsu(e)
    hi = e > thr
    if hi.sum() < 20:
        return None
    e_myo, m_myo = float(np.median(e[hi])), float(np.median(m[hi]))
    blood = (e < 0.25 * e_myo) & (m > m_myo)
    # Too few untagged bright pixels: no cavity (apical slice) – blood levels are then unused.
    has_blood = int(blood.sum()) >= 10
    e_blood = float(np.median(e[blood])) if has_blood else 0.0
    m_blood = float(np.median(m[blood])) if has_blood else m_myo + 1.0
    rest = ~hi & ~blood & (e < 0.8 * e_myo)
    e_bg = float(np.median(e[rest])) if rest.sum() >= 10 else 0.0
    m_bg = float(np.median(m[rest])) if rest.sum() >= 10 else 0.0
    if e_myo <= max(e_bg, e_blood) * 1.2:
        return None
    return _Levels(e_myo, m_myo, e_blood, m_blood, e_bg, m_bg, has_blood)


def myocardium_score(feat: TagFeatures, lv: _Levels) -> np.ndarray:
    """Per-pixel myocardium score ``min(u, v)``: ≈1 in myocardium, ≈0 in blood and background.

    ``v`` separates myocardium from blood (tag energy up, mean down), ``u`` myocardium from
    background (tag energy and mean both up); each is the average of two normalised linear
    features, so 0.5 is the partial-volume midpoint.
    """
    e, m = feat.energy, feat.mean
    u = 0.5 * (e - lv.e_bg) / (lv.e_myo - lv.e_bg) + 0.5 * (m - lv.m_bg) / max(lv.m_myo - lv.m_bg, 1e-6)
    if lv.has_blood:
        v = 0.5 * (e - lv.e_blood) / (lv.e_myo - lv.e_blood) \
            + 0.5 * (lv.m_blood - m) / max(lv.m_blood - lv.m_myo, 1e-6)
    else:
        v = (e - lv.e_bg) / (lv.e_myo - lv.e_bg)
    return np.minimum(u, v)


# --------------------------------------------------------------------------- rays
def _ray_runs(score: np.ndarray, centre_rc: np.ndarray, angles: np.ndarray, max_radius_px: float,
              min_wall_px: float, max_gap_px: float, blur_px: float | None = None,
              threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """First myocardial run (score > 0.5) along each ray from ``centre_rc``.

    With ``blur_px`` (the feature smoothing σ), the myocardial plateau is re-estimated: a wall of
    width w blurred by σ peaks at only ``2Φ(w/2σ) − 1`` of its plateau, so class levels taken
    from the blurred image under-estimate it and a fixed 0.5 threshold thickens thin walls.
    Each ray's peak over that factor estimates the plateau; the threshold becomes half the
    median plateau and the runs are found again (two passes).

    Returns
    -------
    endo, epi : ndarray, shape (K,)
        Sub-pixel radii (linear interpolation of the half-plateau crossing), px; NaN where a ray has no
        run of at least ``min_wall_px``. Runs separated by gaps < ``max_gap_px`` are merged
        (noise). ``endo = 0`` when the run starts at the centre.
    """
    radii = np.arange(0.0, max_radius_px, RADIAL_STEP_PX)
    dirs = np.stack([np.sin(angles), np.cos(angles)], 1)
    pts = centre_rc[None, None, :] + radii[None, :, None] * dirs[:, None, :]
    s = ndi.map_coordinates(score, [pts[..., 0], pts[..., 1]], order=1, mode="constant", cval=0.0)
    endo, epi = _runs_at(s, radii, threshold, min_wall_px, max_gap_px)
    if blur_px is None:
        return endo, epi
    for _ in range(2):
        ok = np.isfinite(epi)
        if ok.sum() < 5:
            break
        width = (epi - np.nan_to_num(endo))[ok]
        lo = np.searchsorted(radii, np.nan_to_num(endo)[ok])
        hi = np.searchsorted(radii, epi[ok])
        peak = np.array([s[i, a:max(b, a + 1)].max() for i, a, b in zip(np.flatnonzero(ok), lo, hi)])
        # Walls starting at the centre (no cavity) are blurred on one side only.
        half = np.where(np.nan_to_num(endo)[ok] == 0, width, 0.5 * width)
        factor = np.clip(2.0 * _phi(half / blur_px) - 1.0, 0.3, 1.0)
        plateau = float(np.median(peak / factor))
        endo, epi = _runs_at(s, radii, 0.5 * plateau, min_wall_px, max_gap_px)
    return endo, epi


def _phi(x):
    from scipy.special import ndtr
    return ndtr(x)


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
    for i in range(k):  # ≤ a few runs per ray; K = 180
        starts = np.flatnonzero(d[i] == 1)
        ends = np.flatnonzero(d[i] == -1)
        good = np.flatnonzero(ends - starts >= min_len)
        if good.size == 0:
            continue
        a, b = starts[good[0]], ends[good[0]]       # run covers samples [a, b)
        si = s[i]
        if a == 0:
            endo[i] = 0.0
        else:
            endo[i] = radii[a - 1] + step * (thr - si[a - 1]) / max(si[a] - si[a - 1], 1e-9)
        if b >= n:
            epi[i] = radii[-1]
        else:
            epi[i] = radii[b - 1] + step * (si[b - 1] - thr) / max(si[b - 1] - si[b], 1e-9)
    return endo, epi


def _circular_smooth(r: np.ndarray, sigma_rays: float, median: int = 5, closed: bool = True) -> np.ndarray:
    """Median then Gaussian smoothing of a radius profile over rays (the shape prior)."""
    mode = "wrap" if closed else "nearest"
    out = ndi.median_filter(r, size=median, mode=mode)
    return ndi.gaussian_filter1d(out, sigma_rays, mode=mode)


def _robust_fill(r: np.ndarray) -> np.ndarray:
    """Fill NaN rays of a closed profile by periodic linear interpolation."""
    ok = np.isfinite(r)
    if ok.all():
        return r
    idx = np.arange(r.size)
    return np.interp(idx, idx[ok], r[ok], period=r.size)


def polar_mask(shape: tuple[int, int], centre_rc: np.ndarray, angles: np.ndarray, endo: np.ndarray,
               epi: np.ndarray, axis_rc: np.ndarray | None = None, base_level: float = np.inf) -> np.ndarray:
    """Rasterise the polar myocardium ``endo(θ) ≤ ρ ≤ epi(θ)`` (pixel centres), optionally cut
    at ``(x − centre)·axis_rc ≤ base_level`` (LA base). NaN rays are outside.

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
    with np.errstate(invalid="ignore"):
        m = (rho >= lo) & (rho <= hi)
    if axis_rc is not None and np.isfinite(base_level):
        m &= dr * axis_rc[0] + dc * axis_rc[1] <= base_level
    return m


# --------------------------------------------------------------------------- slices
def _fail(shape, reason: str, view: str) -> SliceSegmentation:
    return SliceSegmentation(False, reason, np.zeros(shape, bool), view=view)


def _checked_image(image, view: str):
    """``(float image, None)`` for a usable slice, else ``(None, failed SliceSegmentation)``."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2 or min(img.shape) < 16 or not np.all(np.isfinite(img)):
        return None, _fail(np.shape(img)[:2] if img.ndim >= 2 else (0, 0),
                           "image must be a finite 2-D array of at least 16x16 pixels", view)
    if float(img.std()) == 0.0:
        return None, _fail(img.shape, "image is constant (no signal)", view)
    return img, None


def segment_sa(image: np.ndarray, centre_rc, pixel_spacing_mm: float, *, max_radius_mm: float = 60.0,
               min_wall_mm: float = 2.0, max_invalid_fraction: float = 0.25,
               features: TagFeatures | None = None) -> SliceSegmentation:
    """Segment the myocardium of one ED short-axis tagged image.

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
    features : TagFeatures, optional
        Precomputed :func:`tag_features`.

    Returns
    -------
    SliceSegmentation
        ``ok=False`` with a reason when the slice holds no recognisable annulus (no tags, no
        tagged ring around the centre, implausible wall).
    """
    img, failed = _checked_image(image, "SA")
    if failed is not None:
        return failed
    c = np.asarray(centre_rc, dtype=np.float64)
    feat, lv = _levels_around(img, c, max_radius_mm / pixel_spacing_mm, features)
    if lv is None:
        return _fail(img.shape, "no tagged tissue around the long axis (tag energy flat)", "SA")
    return _sa_from_score(myocardium_score(feat, lv), c, pixel_spacing_mm, max_radius_mm, min_wall_mm,
                          max_invalid_fraction, 0.5 * feat.wavelength_px)


def _sa_from_score(score, c, pixel_spacing_mm, max_radius_mm, min_wall_mm, max_invalid_fraction, blur_px=None):
    img = score
    rmax = max_radius_mm / pixel_spacing_mm
    angles = np.linspace(-np.pi, np.pi, NUM_RAYS, endpoint=False)
    endo, epi = _ray_runs(score, c, angles, rmax, min_wall_mm / pixel_spacing_mm, 1.0 / pixel_spacing_mm,
                          blur_px)
    bad = ~np.isfinite(epi)
    if bad.mean() > max_invalid_fraction:
        return _fail(img.shape, f"no myocardial annulus: {100 * bad.mean():.0f}% of rays from the long axis "
                                f"find no tagged wall within {max_radius_mm:g} mm", "SA")
    if np.mean(epi[~bad] >= rmax - 1) > 0.1:
        return _fail(img.shape, f"tagged region extends beyond {max_radius_mm:g} mm from the long axis "
                                "(no closed epicardium)", "SA")
    endo_s = _circular_smooth(_robust_fill(endo), 2.0)
    epi_s = _circular_smooth(_robust_fill(epi), 2.0)
    endo_s = np.clip(endo_s, 0.0, None)
    wall = (epi_s - endo_s) * pixel_spacing_mm
    if np.median(wall) < min_wall_mm or np.median(wall) > 35.0:
        return _fail(img.shape, f"implausible wall thickness {np.median(wall):.1f} mm", "SA")
    epi_s = np.maximum(epi_s, endo_s + 0.5)
    mask = polar_mask(img.shape, c, angles, endo_s, epi_s)
    return SliceSegmentation(True, "", mask, c, angles, endo_s, epi_s, view="SA")


def segment_la(image: np.ndarray, centre_rc, axis_rc, pixel_spacing_mm: float, *,
               max_radius_mm: float = 80.0, min_wall_mm: float = 2.0, min_arc_deg: float = 150.0,
               features: TagFeatures | None = None) -> SliceSegmentation:
    """Segment the horseshoe myocardium of one ED long-axis tagged image.

    Parameters
    ----------
    image : ndarray, shape (rows, cols)
    centre_rc : array_like, shape (2,)
        A point of the long axis inside the cavity (e.g. mid SA stack), (row, col) px.
    axis_rc : array_like, shape (2,)
        In-plane long-axis direction apex → base, (row, col) (normalised here).
    pixel_spacing_mm : float
    max_radius_mm : float
        Longest ray, mm (must reach the apex from ``centre_rc``).
    min_wall_mm : float
    min_arc_deg : float
        Reject when the contiguous arc of rays that meet myocardium is shorter than this.
    features : TagFeatures, optional

    Returns
    -------
    SliceSegmentation
        With ``base_level`` (px along ``axis_rc`` from the centre) where the horseshoe is cut.
    """
    img, failed = _checked_image(image, "LA")
    if failed is not None:
        return failed
    c = np.asarray(centre_rc, dtype=np.float64)
    ax = np.asarray(axis_rc, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)
    feat, lv = _levels_around(img, c, max_radius_mm / pixel_spacing_mm, features)
    if lv is None:
        return _fail(img.shape, "no tagged tissue around the long axis (tag energy flat)", "LA")
    if not lv.has_blood:
        return _fail(img.shape, "no untagged blood pool on the long axis", "LA")
    return _la_from_score(myocardium_score(feat, lv), c, ax, pixel_spacing_mm, max_radius_mm, min_wall_mm,
                          min_arc_deg, 0.5 * feat.wavelength_px)


def _la_from_score(score, c, ax, pixel_spacing_mm, max_radius_mm, min_wall_mm, min_arc_deg, blur_px=None):
    img = score
    rmax = max_radius_mm / pixel_spacing_mm
    angles = np.linspace(-np.pi, np.pi, NUM_RAYS, endpoint=False)
    endo, epi = _ray_runs(score, c, angles, rmax, min_wall_mm / pixel_spacing_mm, 1.0 / pixel_spacing_mm,
                          blur_px)
    valid = np.isfinite(epi) & (epi < rmax - 1)
    # The horseshoe is the longest circular run of valid rays; it must not include the base
    # direction (the atrium side is open).
    if valid.all() or not valid.any():
        return _fail(img.shape, "no horseshoe: the myocardium found is "
                     + ("closed around the axis point" if valid.any() else "absent"), "LA")
    start = int(np.flatnonzero(~valid)[0])
    rolled = np.roll(valid, -start)
    pad = np.concatenate([[False], rolled, [False]]).astype(np.int8)
    d = np.diff(pad)
    s_idx, e_idx = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    j = int(np.argmax(e_idx - s_idx))
    arc = (np.arange(s_idx[j], e_idx[j]) + start) % NUM_RAYS
    arc_deg = arc.size * 360.0 / NUM_RAYS
    if arc_deg < min_arc_deg:
        return _fail(img.shape, f"horseshoe arc only {arc_deg:.0f} deg (< {min_arc_deg:g})", "LA")
    base_dir = np.arctan2(ax[0], ax[1])
    mid_arc = angles[arc[arc.size // 2]]
    if np.cos(mid_arc - base_dir) > 0:
        return _fail(img.shape, "horseshoe opens toward the apex (long-axis orientation inconsistent)", "LA")
    e_arc = _circular_smooth(endo[arc], 1.5, median=5, closed=False)
    p_arc = _circular_smooth(epi[arc], 1.5, median=5, closed=False)
    # Base level: mid-wall axial coordinate of the two arc ends (each end ray stops at the
    # base plane, where the wall leaves the image plane's myocardium).
    ends = []
    for k in (0, arc.size - 1):
        th = angles[arc[k]]
        rmid = 0.5 * (e_arc[k] + p_arc[k])
        ends.append(rmid * (np.sin(th) * ax[0] + np.cos(th) * ax[1]))
    base_level = float(np.mean(ends))
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
    mask = polar_mask(img.shape, c, angles, endo_full, epi_full, ax, base_level)
    return SliceSegmentation(True, "", mask, c, angles, endo_full, epi_full, view="LA",
                             base_level=base_level, axis_rc=ax)


def segment_from_mask(mask: np.ndarray, centre_rc, pixel_spacing_mm: float, axis_rc=None,
                      max_radius_mm: float | None = None) -> SliceSegmentation:
    """Polar contours of a given myocardium mask (user labels), with the same ray machinery.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    centre_rc : array_like, shape (2,)
        Long-axis point in the slice, (row, col) px.
    pixel_spacing_mm : float
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
    if axis_rc is None:
        out = _sa_from_score(score, c, pixel_spacing_mm, max_radius_mm or 60.0, 1.0, 0.25)
    else:
        ax = np.asarray(axis_rc, dtype=np.float64)
        out = _la_from_score(score, c, ax / np.linalg.norm(ax), pixel_spacing_mm, max_radius_mm or 80.0, 1.0, 150.0)
    if out.ok:
        out.mask = m
    out.source = "mask"
    return out


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice overlap of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    s = a.sum() + b.sum()
    return 1.0 if s == 0 else float(2.0 * np.logical_and(a, b).sum() / s)

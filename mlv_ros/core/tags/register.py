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
Tag points refined by registering each track's ED neighbourhood to a later phase.

The Gabor phase locates an intersection from a filter response about one tag period wide. Where
the wall deforms unevenly across that width (the endo- and epicardium at end-systole thicken and
shorten unlike mid-wall) or the wall ends within it, the response's phase is an average of
differently stretched tags and the intersection is read toward mid-wall (measured on bench
studies: a radial bias of +1.3 / +0.8 / −0.1 / −0.9 mm by wall quarter, endo → epi). Here each
track's own ED neighbourhood, inside the ED wall mask, is registered to the later image with a
local affine map and a linear intensity change (tags fade with T1: a tagged tissue's intensity
is ``a·I_ED + b``), Lucas–Kanade style: the ED point's image under the fitted map is where its
material is now, whatever the pattern's shape (any SPAMM profile), without a mask at the later
phase (the ED mask moves with the material).

References
----------
Lucas, B. D., Kanade, T. "An iterative image registration technique with an application to
stereo vision." IJCAI 1981, 674–679 (forward-additive Gauss–Newton image alignment).
Baker, S., Matthews, I. IJCV 56(3):221–255, 2004 (affine warps, Levenberg–Marquardt damping).

"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

# Levenberg–Marquardt damping: the diagonal of the normal equations is raised by this share.
DAMPING = 0.1
# Largest change per Gauss–Newton step: the point moves at most 1 px and each entry of the local
# map at most 0.1 (a tenth of the identity), so one step never jumps to a neighbouring tag.
MAX_STEP_PX = 1.0
MAX_MAP_STEP = 0.1
# The local map is held toward its start (the tracks' own warp) with this share of the map's
# curvature in the data: alone, a template of a few tag cells can shrink onto one dark
# intersection (a degenerate fit measured on bench studies: area ratio → 0.1).
MAP_PRIOR = 0.1
# A fit is kept only when its local map stays a plausible tissue deformation: area change within
# [1/4, 4] (myocardium is near-incompressible; in-plane area changes by less than ×2 through a
# cycle).
MIN_AREA_RATIO = 0.25
MAX_AREA_RATIO = 4.0


def _sample(image: np.ndarray, x: np.ndarray, G: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """
    Return bicubic samples of ``image`` at the template pixels' positions ``x + G y``; NaN outside.

    ``x`` (N, 2) the points (row, col), px, ``G`` (N, 2, 2) their local maps, ``Y`` (N, P, 2) the
    template offsets, px. ``image`` is (H, W), or (H, W, C) float32 with C ≤ 4 channels sampled
    in one pass; the samples are (N, P) or (N, P, C), float64. Bicubic, not bilinear: a tag
    pattern of 4–5 px per period is biased by linear interpolation. The positions are spelled
    out per entry of the 2×2 maps (a batched ``einsum`` costs more than the rest of a
    Gauss–Newton step, with the same sums) and go to OpenCV as float32 maps directly.
    """
    y0, y1 = Y[..., 0], Y[..., 1]
    rows = x[:, 0, None] + (G[:, 0, 0, None] * y0 + G[:, 0, 1, None] * y1)
    cols = x[:, 1, None] + (G[:, 1, 0, None] * y0 + G[:, 1, 1, None] * y1)
    out = cv2.remap(
        image,
        cols.astype(np.float32).reshape(-1, 1),
        rows.astype(np.float32).reshape(-1, 1),
        cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(np.nan,) * 4,
    )
    return out.reshape(rows.shape + image.shape[2:]).astype(np.float64)


def register_points(
    ed_image,
    ed_mask,
    image,
    ed_rc,
    start_rc,
    start_map=None,
    *,
    period_px: float,
    radius: float = 1.0,
    sigma: float = 0.5,
    smoothing: float = 0.1,
    iterations: int = 8,
    map_prior: float = MAP_PRIOR,
):
    """
    Locate ED points in a later image by a local affine registration of their ED neighbourhood.

    For each point, ``Σ_y w(y) [I(x + G y) − (a I_ED(x_ED + y) + b)]²`` is minimised over its
    position ``x``, local map ``G`` (2×2) and intensity change ``a, b`` (damped Gauss–Newton),
    ``y`` the integer-pixel offsets within ``radius`` periods of the ED point that lie inside the
    ED mask, ``w`` a Gaussian of ``sigma`` periods.

    Parameters
    ----------
    ed_image : array_like, shape (H, W)
        The ED image of the slice.
    ed_mask : array_like of bool, shape (H, W)
        The ED myocardium (the template's support: blood and background do not move with it).
    image : array_like, shape (H, W)
        The later image.
    ed_rc : ndarray, shape (N, 2)
        ED (row, col) of the points, px.
    start_rc : ndarray, shape (N, 2)
        Starting (row, col) in the later image, px (e.g. the matched detections).
    start_map : ndarray, shape (N, 2, 2), optional
        Starting local map ∂x/∂x_ED (e.g. the Jacobian of the tracks' warp); default identity.
    period_px : float
        Tag period, px: ``radius`` and ``sigma`` are in periods (the pattern's own scale).
    radius, sigma : float
        Template radius and Gaussian weight width, tag periods.
    smoothing : float
        Both images are smoothed by a Gaussian of this many tag periods first (0: none): the
        tags' band is kept, the pixel noise above it is not fitted.
    iterations : int
        Gauss–Newton steps (at least 1).
    map_prior : float
        Weight holding the local map at ``start_map``, as a share of the map's own curvature in
        the data (``MAP_PRIOR``; large values fit only the position and intensity change).

    Returns
    -------
    rc : ndarray, shape (N, 2)
        Registered (row, col), px (``start_rc`` where not ``ok``).
    local_map : ndarray, shape (N, 2, 2)
        Fitted ∂x/∂x_ED.
    ok : ndarray of bool, shape (N,)
        The fit used at least a fifth of the template's weight (the rest outside the ED wall or
        the image) and its map's area ratio is within [MIN_AREA_RATIO, MAX_AREA_RATIO].
    ncc : ndarray, shape (N,)
        Weighted normalised cross-correlation of the template and the fitted image samples.

    Raises
    ------
    ValueError
        When shapes disagree, ``period_px``, ``radius`` or ``sigma`` is not positive or
        ``smoothing`` is negative.

    """
    ed, im, msk, x0, x, G = _checked_inputs(
        ed_image, ed_mask, image, ed_rc, start_rc, start_map, period_px, radius, sigma,
        smoothing, map_prior,
    )
    n = len(x0)
    if n == 0:
        return x, G, np.zeros(0, bool), np.zeros(0)
    T, W, Y, w0 = _template(ed, msk, x0, period_px, radius, sigma)
    ok = W.sum(axis=1) >= 0.2 * w0.sum()
    x, G = _gauss_newton(im, T, W, Y, x, G, ok, iterations, map_prior)
    val = _sample(im, x, G, Y)
    w = np.where(np.isfinite(val), W, 0.0)
    ncc = _ncc(w, T, np.nan_to_num(val))
    area = np.linalg.det(G)
    ok &= (
        (area >= MIN_AREA_RATIO)
        & (area <= MAX_AREA_RATIO)
        & np.all(np.isfinite(x), axis=1)
        & (w.sum(axis=1) >= 0.2 * w0.sum())
    )
    x = np.where(ok[:, None], x, np.asarray(start_rc, float).reshape(-1, 2))
    return x, G, ok, ncc


def _checked_inputs(
    ed_image, ed_mask, image, ed_rc, start_rc, start_map, period_px, radius, sigma, smoothing,
    map_prior,
):
    """Check :func:`register_points`' inputs; return its images (smoothed), points and maps."""
    ed = np.asarray(ed_image, np.float32)
    im = np.asarray(image, np.float32)
    msk = np.asarray(ed_mask, bool)
    if ed.ndim != 2 or ed.shape != im.shape or msk.shape != ed.shape:
        raise ValueError(
            f'ed_image, ed_mask and image must be 2-D of one shape; got {ed.shape}, '
            f'{msk.shape}, {im.shape}'
        )
    if not (period_px > 0 and radius > 0 and sigma > 0 and smoothing >= 0 and map_prior >= 0):
        raise ValueError(
            f'period_px, radius and sigma must be positive, smoothing and map_prior ≥ 0; got '
            f'{period_px}, {radius}, {sigma}, {smoothing}, {map_prior}'
        )
    if smoothing > 0:  # both images alike: the band of the tags, not the pixel noise
        ed = cv2.GaussianBlur(ed, (0, 0), smoothing * period_px)
        im = cv2.GaussianBlur(im, (0, 0), smoothing * period_px)
    x0 = np.asarray(ed_rc, float).reshape(-1, 2)
    x = np.array(start_rc, float).reshape(-1, 2)
    n = len(x0)
    if x.shape != x0.shape:
        raise ValueError(f'start_rc {x.shape} must match ed_rc {x0.shape}')
    G = (
        np.tile(np.eye(2), (n, 1, 1))
        if start_map is None
        else np.array(start_map, float).reshape(n, 2, 2)
    )
    return ed, im, msk, x0, x, G


def _template(ed, msk, x0, period_px: float, radius: float, sigma: float):
    """
    Return each point's ED template: intensities, weights, offsets and the disc's weights.

    ``T`` (N, P) the ED intensities at the integer pixels within ``radius`` periods, ``W`` (N, P)
    their Gaussian weights where inside the image and the ED wall, ``Y`` (N, P, 2) the pixels'
    offsets from the ED point itself, ``w0`` (P,) the full disc's weights.
    """
    offs, w0 = _disc(float(period_px), float(radius), float(sigma))
    base = np.rint(x0)
    pix = (base[:, None, :] + offs[None]).astype(int)  # (N, P, 2) template pixels
    inside = np.all((pix >= 0) & (pix < np.array(ed.shape)), axis=2)
    pr = np.clip(pix[..., 0], 0, ed.shape[0] - 1)
    pc = np.clip(pix[..., 1], 0, ed.shape[1] - 1)
    T = ed[pr, pc].astype(np.float64)
    W = w0[None] * (inside & msk[pr, pc])
    Y = offs[None] - (x0 - base)[:, None, :]  # offsets from the ED point itself
    return T, W, Y, w0


@lru_cache(maxsize=32)
def _disc(period_px: float, radius: float, sigma: float):
    """
    Return the template disc: integer offsets within ``radius`` periods and their weights.

    ``offs`` (P, 2) px and ``w0`` (P,), read-only; remembered (one disc per slice's period).
    """
    half = int(np.ceil(radius * period_px))
    o = np.arange(-half, half + 1, dtype=float)
    offs = np.stack(np.meshgrid(o, o, indexing='ij'), -1).reshape(-1, 2)
    offs = offs[np.hypot(offs[:, 0], offs[:, 1]) <= radius * period_px]
    w0 = np.exp(-0.5 * np.sum(offs**2, axis=1) / (sigma * period_px) ** 2)
    for a in (offs, w0):
        a.setflags(write=False)
    return offs, w0


def _gauss_newton(im, T, W, Y, x, G, ok, iterations: int, map_prior: float):
    """
    Run :func:`register_points`' damped Gauss–Newton steps; return the positions and maps.

    Unknowns per point: position (2), local map (4) and intensity gain and offset (2); the map
    is held toward its start by ``map_prior`` times its own curvature at the start; steps are
    capped (``MAX_STEP_PX``, ``MAX_MAP_STEP``), and points not ``ok`` do not move.
    """
    G0 = G.copy()
    gr, gc = np.gradient(im)
    # The image and its gradient sampled in one remap (bit-identical to three), interleaved by
    # OpenCV (the same array as np.dstack, in a third of its time)
    stack = cv2.merge([im, gr.astype(np.float32, copy=False), gc.astype(np.float32, copy=False)])
    n = len(x)
    a, b = np.ones(n), np.zeros(n)
    y0, y1 = Y[..., 0], Y[..., 1]
    diag = np.arange(8)
    # Jacobian of the residual by (x, G, a, b), (N, P, 8); the intensity columns are fixed
    jac = np.empty(T.shape + (8,))
    jac[..., 6] = -T
    jac[..., 7] = -1.0
    for it in range(max(1, int(iterations))):
        s = _sample(stack, x, G, Y)
        inside = np.isfinite(s)
        if inside.all():  # no template pixel off the image (or the usual case, at once)
            w = W
        else:
            w = np.where(inside[..., 0], W, 0.0)
            s = np.where(inside, s, 0.0)
        val, dr, dc = s[..., 0], s[..., 1], s[..., 2]
        if it == 0:  # the intensity change from a weighted linear fit at the start
            a, b = _linear_fit(w, T, val)
        res = val - (a[:, None] * T + b[:, None])
        jac[..., 0], jac[..., 1] = dr, dc
        np.multiply(dr, y0, out=jac[..., 2])
        np.multiply(dr, y1, out=jac[..., 3])
        np.multiply(dc, y0, out=jac[..., 4])
        np.multiply(dc, y1, out=jac[..., 5])
        # Σ_p w Jᵀ J and Σ_p w Jᵀ r as batched matmuls: ~5–10× faster than three-operand
        # einsums (the same sums in another order: points within 1e-13 px)
        jwt = (jac * w[..., None]).transpose(0, 2, 1)
        H = np.matmul(jwt, jac)
        g = np.matmul(jwt, res[..., None])[..., 0]
        if it == 0:  # the prior's weight: the map block's own curvature at the start
            prior = map_prior * np.diagonal(H, axis1=1, axis2=2)[:, 2:6].mean(axis=1)
        H[:, 2:6, 2:6] += prior[:, None, None] * np.eye(4)
        g[:, 2:6] += prior[:, None] * (G - G0).reshape(-1, 4)
        H[:, diag, diag] += DAMPING * H[:, diag, diag]
        H[:, diag, diag] += 1e-9 * (np.trace(H, axis1=1, axis2=2)[:, None] + 1e-30)
        d = -np.linalg.solve(H, g[..., None])[..., 0]
        scale = np.minimum(
            MAX_STEP_PX / np.maximum(np.linalg.norm(d[:, :2], axis=1), 1e-12),
            MAX_MAP_STEP / np.maximum(np.abs(d[:, 2:6]).max(axis=1), 1e-12),
        )
        d = d * np.where(ok, np.minimum(scale, 1.0), 0.0)[:, None]
        x = x + d[:, :2]
        G = G + d[:, 2:6].reshape(-1, 2, 2)
        a, b = a + d[:, 6], b + d[:, 7]
    return x, G


def _linear_fit(w, t, v):
    """Weighted least-squares ``v ≈ a t + b`` per row; returns ``(a, b)``, shape (N,) each."""
    sw = np.maximum(w.sum(axis=1), 1e-30)
    mt, mv = (w * t).sum(axis=1) / sw, (w * v).sum(axis=1) / sw
    var = (w * (t - mt[:, None]) ** 2).sum(axis=1) / sw
    a = (w * (t - mt[:, None]) * (v - mv[:, None])).sum(axis=1) / sw / np.maximum(var, 1e-30)
    return a, mv - a * mt


def _ncc(w, t, v):
    """Weighted normalised cross-correlation per row, shape (N,)."""
    sw = np.maximum(w.sum(axis=1), 1e-30)
    dt = t - ((w * t).sum(axis=1) / sw)[:, None]
    dv = v - ((w * v).sum(axis=1) / sw)[:, None]
    cov = (w * dt * dv).sum(axis=1)
    return cov / np.sqrt(np.maximum((w * dt**2).sum(axis=1) * (w * dv**2).sum(axis=1), 1e-30))

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
Contours, curvature and curvature-based landmarks.

Paper §3.2: "50 per SA slice … on the myocardial contours based on local curvature".

A landmark set keeps the points where the contour bends most (extrema of the signed curvature,
strongest first, at least ``min_separation`` apart) and fills the remainder by farthest-point
sampling in arc length, so the landmarks both pin the distinctive features (corners, notches,
vertices of an ellipse) and cover the whole contour. On a circle (constant curvature) the set
degenerates gracefully to evenly spaced points.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

#: Landmarks per SA slice in the paper (split between endo- and epicardium here).
LANDMARKS_PER_SA_SLICE = 50


def _as_curve(points, name: str = 'contour') -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 5:
        raise ValueError(f'{name} must have shape (K, 2) with K >= 5, got {p.shape}')
    if not np.all(np.isfinite(p)):
        raise ValueError(f'{name} contains NaN/inf')
    return p


def resample_contour(points, n: int, closed: bool = True) -> np.ndarray:
    """
    Resample a polyline to ``n`` points evenly spaced in arc length.

    Parameters
    ----------
    points : array_like, shape (K, 2)
        Polyline vertices.
    n : int
        Number of output points.
    closed : bool
        Treat the last vertex as joined to the first.

    Returns
    -------
    ndarray, shape (n, 2)

    """
    p = _as_curve(points)
    if n < 2:
        raise ValueError(f'n must be >= 2, got {n}')
    q = np.vstack([p, p[:1]]) if closed else p
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    t = np.linspace(0.0, s[-1], n, endpoint=not closed)
    return np.stack([np.interp(t, s, q[:, 0]), np.interp(t, s, q[:, 1])], axis=1)


def curvature(points, closed: bool = True, sigma: float = 2.0) -> np.ndarray:
    """
    Signed curvature κ = (x′y″ − y′x″)/(x′² + y′²)^{3/2} of a polyline.

    The curve is Gaussian-smoothed (``sigma`` vertices, periodic when ``closed``) and then
    differentiated by central differences (exact ratio of first/second derivative scales), so
    the input should be roughly evenly spaced (see :func:`resample_contour`).

    Returns
    -------
    ndarray, shape (K,)
        1 / (units of ``points``); positive where the curve turns toward increasing angle
        (counter-clockwise in a right-handed (x, y) plane).

    """
    p = _as_curve(points)
    mode = 'wrap' if closed else 'nearest'
    sm = np.stack([ndi.gaussian_filter1d(p[:, i], sigma, mode=mode) for i in (0, 1)], 1)
    if closed:
        fwd, bwd = np.roll(sm, -1, axis=0), np.roll(sm, 1, axis=0)
    else:
        fwd = np.vstack([sm[1:], 2 * sm[-1:] - sm[-2:-1]])
        bwd = np.vstack([2 * sm[:1] - sm[1:2], sm[:-1]])
    d1 = 0.5 * (fwd - bwd)
    d2 = fwd - 2 * sm + bwd
    num = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    den = np.maximum(np.sum(d1**2, axis=1), 1e-24) ** 1.5
    return num / den


def curvature_landmarks(
    points,
    n: int,
    closed: bool = True,
    sigma: float = 2.0,
    feature_fraction: float = 0.5,
    min_separation: int | None = None,
) -> np.ndarray:
    """
    Return the indices of ``n`` landmarks on a contour, chosen by local curvature.

    See the module docstring.

    Parameters
    ----------
    points : array_like, shape (K, 2)
        Evenly spaced contour vertices (K ≥ n).
    n : int
        Number of landmarks.
    closed : bool
        Treat the last vertex as joined to the first.
    sigma : float
        Curvature smoothing, vertices.
    feature_fraction : float
        At most this fraction of the landmarks are curvature extrema; the rest fill the gaps.
    min_separation : int, optional
        Minimum index distance between two curvature landmarks (default ``K // (2 n)``, ≥ 1).

    Returns
    -------
    ndarray of int, shape (n,)
        Sorted vertex indices.

    Raises
    ------
    ValueError
        ``n`` < 1 or larger than the number of vertices.

    """
    p = _as_curve(points)
    k = p.shape[0]
    if not 1 <= n <= k:
        raise ValueError(f'number of landmarks must be in [1, {k}], got {n}')
    kap = curvature(p, closed, sigma)
    dev = np.abs(kap - np.median(kap))
    mode = 'wrap' if closed else 'nearest'
    # Local extrema of κ (either sign): κ equals the running max or min over ±2 vertices.
    is_ext = (kap == ndi.maximum_filter1d(kap, 5, mode=mode)) | (
        kap == ndi.minimum_filter1d(kap, 5, mode=mode)
    )
    # Significant: well above the curvature noise (median absolute deviation).
    mad = np.median(dev) + 1e-12
    cand = np.flatnonzero(is_ext & (dev > 3.0 * mad) & (dev > 1e-3 * (np.abs(kap).max() + 1e-12)))
    cand = cand[np.argsort(-dev[cand])]
    sep = max(int(min_separation if min_separation is not None else k // (2 * n)), 1)
    chosen: list[int] = []
    for c in cand:
        if len(chosen) >= int(feature_fraction * n):
            break
        d = np.abs(np.array(chosen) - c) if chosen else np.array([k])
        if closed and chosen:
            d = np.minimum(d, k - d)
        if np.all(d >= sep):
            chosen.append(int(c))
    # Farthest-point fill in arc length.
    q = np.vstack([p, p[:1]]) if closed else p
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])
    total, s = s[-1], s[:k]
    if not chosen:
        chosen = [0] if closed else [0, k - 1][:n]
    dist = np.full(k, np.inf)
    for c in chosen:
        d = np.abs(s - s[c])
        dist = np.minimum(dist, np.minimum(d, total - d) if closed else d)
    while len(chosen) < n:
        c = int(np.argmax(dist))
        chosen.append(c)
        d = np.abs(s - s[c])
        dist = np.minimum(dist, np.minimum(d, total - d) if closed else d)
    return np.sort(np.array(chosen[:n], dtype=np.int64))

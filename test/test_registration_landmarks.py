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

"""Curvature landmarks on analytic shapes; polar-coordinate round trips of the model frame."""

from mlv_ros.core.registration.initialise import (
    AxisFrame,
    default_reference,
    model_frame,
    polar_to_patient,
    reconstruct_shape,
)
from mlv_ros.core.registration.landmarks import curvature, curvature_landmarks, resample_contour
import numpy as np
import pytest


def _ellipse(a=30.0, b=15.0, n=400):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([a * np.cos(t), b * np.sin(t)], 1), t


def test_curvature_of_circle_and_ellipse():
    t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    circ = 20.0 * np.stack([np.cos(t), np.sin(t)], 1)
    assert np.allclose(curvature(circ), 1 / 20.0, rtol=1e-3)
    pts, t = _ellipse()
    k = curvature(pts, sigma=1.0)
    exact = 30 * 15 / ((30 * np.sin(t)) ** 2 + (15 * np.cos(t)) ** 2) ** 1.5
    # Vertices: a/b² at the major-axis ends, b/a² at the minor-axis ends (1 % tolerance).
    assert np.allclose(k, exact, rtol=0.01)


def test_ellipse_landmarks_hit_the_four_vertices():
    pts, t = _ellipse()
    idx = curvature_landmarks(pts, 12)
    assert idx.size == 12 and np.all(np.diff(idx) > 0)
    for vertex in (0, 100, 200, 300):  # t = 0, π/2, π, 3π/2
        d = np.abs(idx - vertex)
        assert np.min(np.minimum(d, 400 - d)) <= 2


def test_circle_with_notch_landmarks_mark_the_notch_and_cover_the_rest():
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    r = np.where(np.abs(t - np.pi) < 0.15, 17.0, 20.0)  # 3 mm deep notch around t = π
    pts = resample_contour(np.stack([r * np.cos(t), r * np.sin(t)], 1), 360)
    idx = curvature_landmarks(pts, 25)
    ang = np.arctan2(pts[idx, 1], pts[idx, 0]) % (2 * np.pi)
    # Both notch corners (t = π ± 0.15) carry a landmark within 0.05 rad.
    for corner in (np.pi - 0.15, np.pi + 0.15):
        assert np.min(np.abs(ang - corner)) < 0.05
    # Coverage: no gap between consecutive landmarks larger than 3× the even spacing.
    gaps = np.diff(np.sort(np.concatenate([ang, [ang.min() + 2 * np.pi]])))
    assert gaps.max() < 3 * 2 * np.pi / 25


def test_landmarks_reject_bad_input():
    pts, _ = _ellipse(n=20)
    with pytest.raises(ValueError, match='number of landmarks'):
        curvature_landmarks(pts, 21)
    with pytest.raises(ValueError, match='NaN'):
        curvature_landmarks(np.full((10, 2), np.nan), 3)


def _prolate_shape():
    """Analytic truncated prolate shell (epi 39/85 mm, endo 30/76 mm) as contour points."""
    axis = np.array([0.0, 0.0, 1.0])
    frame = AxisFrame(np.zeros(3), axis, default_reference(axis))
    zs = np.linspace(0.5, 85, 60)
    th = np.linspace(-np.pi, np.pi, 48, endpoint=False)
    Z, T = np.meshgrid(zs, th, indexing='ij')

    def pts(a, c):
        r = a * np.sqrt(np.clip(1 - ((85 - Z) / c) ** 2, 0, None))
        keep = r > 0
        return frame.from_cylindrical(r[keep], T[keep], Z[keep])

    return frame, pts(39.0, 85.0), pts(30.0, 76.0)


def test_polar_coordinate_round_trip():
    frame, epi, endo = _prolate_shape()
    shape = reconstruct_shape(frame, [endo], [epi], 85.0)
    rng = np.random.default_rng(0)
    x = frame.from_cylindrical(
        rng.uniform(5, 35, 500), rng.uniform(-np.pi, np.pi, 500), rng.uniform(10, 80, 500)
    )
    mf, polar = model_frame(shape, x)
    assert np.all((polar['w'] >= 0) & (polar['w'] <= 1 + 1e-12)) and np.isclose(
        polar['w'].max(), 1.0
    )
    assert np.all(np.abs(polar['beta']) <= np.pi)
    back = polar_to_patient(mf, polar['alpha'], polar['beta'], polar['w'])
    assert np.max(np.abs(back - x)) < 1e-9


def test_reconstruction_of_analytic_prolate_and_alpha_range():
    frame, epi, endo = _prolate_shape()
    shape = reconstruct_shape(frame, [endo], [epi], 85.0)
    assert abs(shape.z_apex_epi - 0.0) < 1.0 and abs(shape.z_apex_endo - 9.0) < 1.5
    # Radii within 0.5 mm at mid-ventricle.
    z, th = np.full(8, 45.0), np.linspace(-np.pi, np.pi, 8, endpoint=False)
    assert np.allclose(np.sqrt(shape.epi.r2(z, th)), 39 * np.sqrt(1 - (40 / 85) ** 2), atol=0.5)
    ep = shape.surface_points('epi')
    _, polar = model_frame(shape, ep)
    # α runs from −π/2 at the apex up to at most ≈ π/4 on the epicardial base rim (paper §2.1;
    # the least-squares ellipsoid leaves the rim slightly inside, so α_max is a little lower).
    assert polar['alpha'].min() < -np.pi / 2 + 0.1
    assert np.pi / 6 < polar['alpha'].max() <= np.pi / 4 + 0.05

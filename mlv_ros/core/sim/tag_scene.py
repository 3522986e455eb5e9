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
Analytic tagged-image scenes with exact ground truth (tests and benchmark fallback).

A scene is a 1-1 SPAMM grid ``P(X) = Π_d sin²(k_d·(X − c)/2)`` laid in material coordinates
``X`` (pixels, the ED image frame, ``c`` the image centre), an annulus of "myocardium" around a
bright untagged "blood pool", tagged static background, and a smooth forward motion
``x = φ(X, t)`` (scaling, rotation, translation and a sinusoidal non-affine term). Tag
intersections are the material points with ``k_d·(X − c) ∈ 2πℤ`` for both ``d``; their image
positions at any ``t`` are ``φ(X, t)`` exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TagScene:
    """
    Synthetic tagged cine of one slice.

    Attributes
    ----------
    shape : (int, int)
        Image rows, cols.
    spacing_px : float
        Tag spacing at ED, px.
    angles : (float, float)
        Wave-vector angles, rad (package conventions).
    ring : (float, float)
        Inner and outer radius of the myocardial annulus at ED, px (around the image centre).
    scale, rotation_deg, shift, wobble : float, float, (float, float), float
        Peak motion (at ``t = 0.5``): radial scale change (−0.1 = 10 % contraction), rotation,
        translation (px) and amplitude of the non-affine term (px).
    t1_fraction : float
        Tag contrast ``exp(−t/t1_fraction)`` at cycle fraction ``t`` (inf = no fading).
    blood, myocardium, background : float
        Untagged intensities.
    noise_sigma : float
        Standard deviation of additive Gaussian noise (myocardium intensity units).

    """

    shape: tuple = (128, 128)
    spacing_px: float = 6.0
    angles: tuple = (0.0, np.pi / 2)
    ring: tuple = (18.0, 34.0)
    scale: float = -0.08
    rotation_deg: float = 8.0
    shift: tuple = (1.0, -0.5)
    wobble: float = 0.8
    t1_fraction: float = np.inf
    blood: float = 1.3
    myocardium: float = 1.0
    background: float = 0.6
    noise_sigma: float = 0.0

    @property
    def centre(self) -> np.ndarray:
        return (np.asarray(self.shape, float) - 1) / 2

    @property
    def wavevectors(self) -> np.ndarray:
        a = np.asarray(self.angles, float)
        return 2 * np.pi / self.spacing_px * np.stack([np.sin(a), np.cos(a)], -1)

    def _amp(self, t):
        return 0.5 * (1 - np.cos(2 * np.pi * t))

    def forward(self, X: np.ndarray, t: float) -> np.ndarray:
        """Image position at cycle fraction ``t`` of material points ``X``, shape (N, 2), px."""
        a = self._amp(t)
        c = self.centre
        th = np.deg2rad(self.rotation_deg * a)
        rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        d = np.asarray(X, float) - c
        u = self.wobble * a * np.stack([np.sin(d[:, 1] / 15.0), np.cos(d[:, 0] / 18.0)], -1)
        return c + (1 + self.scale * a) * d @ rot.T + a * np.asarray(self.shift) + u

    def inverse(self, x: np.ndarray, t: float, iterations: int = 30) -> np.ndarray:
        """
        Return the material points of image points ``x``, shape (N, 2).

        Fixed-point inversion of :meth:`forward`; converges because the non-affine term is a
        contraction.
        """
        x = np.asarray(x, float)
        a = self._amp(t)
        c = self.centre
        th = np.deg2rad(self.rotation_deg * a)
        rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        s = 1 + self.scale * a
        X = x.copy()
        for _ in range(iterations):
            d = X - c
            u = self.wobble * a * np.stack([np.sin(d[:, 1] / 15.0), np.cos(d[:, 0] / 18.0)], -1)
            X = c + ((x - c - a * np.asarray(self.shift) - u) @ rot) / s
        return X

    def pattern(self, X: np.ndarray) -> np.ndarray:
        """SPAMM grid at material points, in [0, 1] (0 on tag lines)."""
        ph = (np.asarray(X, float) - self.centre) @ self.wavevectors.T
        return np.prod(np.sin(ph / 2) ** 2, axis=-1)

    def _radius(self, X):
        return np.linalg.norm(np.asarray(X, float) - self.centre, axis=-1)

    def myocardium_mask(self, t: float = 0.0) -> np.ndarray:
        """Pixels whose material lies in the ED annulus, bool (rows, cols)."""
        pix = np.indices(self.shape).reshape(2, -1).T.astype(float)
        r = self._radius(self.inverse(pix, t))
        return ((r >= self.ring[0]) & (r <= self.ring[1])).reshape(self.shape)

    def render(self, t: float = 0.0, seed: int | None = 0) -> np.ndarray:
        """Image at cycle fraction ``t``, float64 (rows, cols)."""
        pix = np.indices(self.shape).reshape(2, -1).T.astype(float)
        X = self.inverse(pix, t)
        r = self._radius(X)
        fade = np.exp(-t / self.t1_fraction) if np.isfinite(self.t1_fraction) else 1.0
        myo = self.myocardium * (fade * self.pattern(X) + 1 - fade)
        bg = self.background * (fade * self.pattern(pix) + 1 - fade)  # static tissue
        img = np.where(r < self.ring[0], self.blood, np.where(r <= self.ring[1], myo, bg))
        img = img.reshape(self.shape)
        if self.noise_sigma > 0:
            img = img + self.noise_sigma * np.random.default_rng(seed).standard_normal(self.shape)
        return img

    def intersections(self, margin: float = 0.0):
        """
        ED tag intersections inside the annulus shrunk by ``margin`` px.

        Returns
        -------
        X : ndarray, shape (N, 2)
            Material (= ED image) positions, px.
        labels : ndarray of int, shape (N, 2)
            (k1, k2) with ``k_d·(X − c) = 2π k_d``.

        """
        n = int(np.ceil(max(self.shape) / self.spacing_px)) + 2
        k1, k2 = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing='ij')
        lab = np.stack([k1.ravel(), k2.ravel()], -1)
        X = self.centre + np.linalg.solve(self.wavevectors, 2 * np.pi * lab.T).T
        r = self._radius(X)
        keep = (r >= self.ring[0] + margin) & (r <= self.ring[1] - margin)
        return X[keep], lab[keep]

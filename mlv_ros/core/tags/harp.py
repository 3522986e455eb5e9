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
HARP baseline: harmonic phase images and phase-constancy point tracking.

One spectral peak per tag direction is isolated with a band-pass filter; the phase of the
inverse transform (the harmonic phase) is a material property, so a point is tracked from phase
``t`` to ``t+1`` by solving ``wrap(a(y, t+1) − a(y₀, 0)) = 0`` with Newton's method starting at its
previous position (Osman et al. 1999, eq. 9). Used by the benchmark as the reference tracker.

References
----------
Osman, N. F., Kerwin, W. S., McVeigh, E. R., Prince, J. L. "Cardiac motion tracking using CINE
harmonic phase (HARP) magnetic resonance imaging." Magn. Reson. Med. 42(6):1048–1060, 1999.

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from .gabor import TagInputError, TagParameters, validate_image
from .phase import PhaseField, solve_phase


def harmonic_phase(image, params: TagParameters, bandwidth: float = 0.35) -> PhaseField:
    """
    Harmonic phase of both tag directions.

    The band-pass filter of direction ``d`` is a Gaussian in frequency centred on the fundamental
    ``f_d = 1/λ_d`` with standard deviation ``bandwidth·|f_d|`` (an isotropic stand-in for HARP's
    circular filter, without the ringing of a hard edge).

    Parameters
    ----------
    image : array_like, shape (H, W)
        Tagged image.
    params : TagParameters
        Fundamental frequencies (typically estimated at ED and reused).
    bandwidth : float
        Filter standard deviation relative to the peak frequency.

    Returns
    -------
    PhaseField
        Wrapped harmonic phases (≡ π on dark tags, as for the Gabor phase) and their Jacobian.

    """
    img = np.asarray(image, np.float64)
    h, w = img.shape
    spec = sfft.fft2(img - img.mean())
    fr = sfft.fftfreq(h)[:, None]
    fc = sfft.fftfreq(w)[None, :]
    out = np.empty((2, h, w), np.complex128)
    for d in range(2):
        f0 = params.wavevectors[d] / (2 * np.pi)  # cycles/px, (row, col)
        sig = bandwidth * np.hypot(*f0)
        filt = np.exp(-((fr - f0[0]) ** 2 + (fc - f0[1]) ** 2) / (2 * sig**2))
        out[d] = sfft.ifft2(spec * filt)
    return PhaseField.from_complex(out)


@dataclass
class HarpTrack:
    """
    HARP trajectories of a set of points.

    Attributes
    ----------
    pixel_rc : ndarray, shape (T, N, 2)
        Position per phase, px (NaN once lost).
    valid : ndarray of bool, shape (T, N)
    reason : str
        Empty on success, else why nothing was tracked.

    """

    pixel_rc: np.ndarray
    valid: np.ndarray
    reason: str = ''


def harp_track(
    images,
    start_rc,
    params: TagParameters,
    bandwidth: float = 0.35,
    max_residual: float = 0.5,
    max_step_px: float | None = None,
) -> HarpTrack:
    """
    Track points through a cine with HARP phase constancy (never raises on bad images).

    Parameters
    ----------
    images : sequence of array_like, each (H, W)
        Frames in phase order; ``images[0]`` holds the points at ``start_rc``.
    start_rc : ndarray, shape (N, 2)
        Initial (row, col), px.
    params : TagParameters
        Tag frequencies (ED estimate).
    bandwidth : float
        See :func:`harmonic_phase`.
    max_residual : float
        A point whose phase residual (rad, both directions) exceeds this is lost from then on.
    max_step_px : float, optional
        Largest Newton step, px (default a quarter of the smaller spacing: HARP cannot tell
        points a whole period apart, so larger jumps are phase slips).

    Returns
    -------
    HarpTrack

    """
    start = np.asarray(start_rc, float).reshape(-1, 2)
    t_n = len(images)
    pos = np.full((t_n, len(start), 2), np.nan)
    valid = np.zeros((t_n, len(start)), bool)
    if t_n == 0 or len(start) == 0:
        return HarpTrack(pos, valid, 'no images or no points')
    if max_step_px is None:
        max_step_px = 0.25 * float(np.min(params.spacing_px))
    try:
        field0 = harmonic_phase(validate_image(images[0]), params, bandwidth)
    except TagInputError as exc:
        return HarpTrack(pos, valid, f'phase 0: {exc}')
    target, _, inside = field0.sample(start)
    pos[0] = start
    valid[0] = inside
    prev = start.copy()
    prev_step = np.zeros_like(start)
    alive = inside.copy()
    for t in range(1, t_n):
        try:
            field = harmonic_phase(validate_image(images[t]), params, bandwidth)
        except TagInputError:
            alive[:] = False
            continue
        # Seed with the previous displacement (as the Gabor/RPM tracker does).
        seed = prev + prev_step
        x, res, ok = solve_phase(field, seed, target, iterations=4, max_step=max_step_px)
        alive &= (
            ok
            & (res <= max_residual)
            & (np.linalg.norm(x - prev, axis=1) <= 2 * max_step_px + 1e-9)
        )
        prev_step = np.where(alive[:, None], x - prev, 0.0)
        prev = np.where(alive[:, None], x, prev)
        pos[t] = np.where(alive[:, None], x, np.nan)
        valid[t] = alive
    return HarpTrack(pos, valid)

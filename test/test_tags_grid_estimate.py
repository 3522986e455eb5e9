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
Tag directions and period from each image's own spectrum, over the acquisition range.

Simulated ED frames (the LV phantom, one sub-plane, SNR 20) with the grid laid at any in-plane
angle, periods 3.5–8 px (5–10 mm tags on 1.0–2.0 mm pixels), with and without tagged tissue
around the heart. Truth: the simulator's grid (``tag_pattern``: tag planes through the image
centre at multiples of the period along directions rotated by ``tag_angle_deg``).
"""

from mlv_ros.core.sim import load_preset, plan_slices
from mlv_ros.core.sim.imaging import ImageSynthesizer
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.tags import detect_intersections, estimate_grid
from mlv_ros.core.types import VIEW_SA
import numpy as np
import pytest
from scipy.spatial import cKDTree

pytestmark = pytest.mark.slow  # about a minute of simulation: scheduled first (conftest)

FOV_MM = 200.0


def _ed_frames(
    angle_deg, pixel_mm, period_mm, background_m0, preset='normal', seed=0, blood_m0=None
):
    """ED image and true myocardium mask of the mid SA slice and of one LA plane."""
    p = load_preset(preset)
    im = p['imaging']
    size = int(round(FOV_MM / pixel_mm))
    im.update(
        tag_angle_deg=angle_deg,
        pixel_spacing_mm=pixel_mm,
        tag_spacing_mm=period_mm,
        background_m0=background_m0,
        size=size,
        subplanes=1,
    )
    if blood_m0 is not None:
        im['blood_m0'] = blood_m0
    motion = LVMotion(p)
    planes = plan_slices(motion, im, size)
    sa = [s for s in planes if s.view == VIEW_SA]
    picks = [sa[len(sa) // 2], [s for s in planes if s.view != VIEW_SA][1]]
    rng = np.random.default_rng(seed)
    out = []
    for plane in picks:
        syn = ImageSynthesizer(motion, plane, size, im)
        out.append((syn.render(0, 0.0, 20.0, rng), syn.tissue_fractions(0)[0] >= 0.5, size))
    return out


def _true_intersections(angle_deg, period_px, size):
    """Grid intersections in (row, col) px: the sim's directions u = (sin a, cos a), v ⟂ u."""
    a = np.radians(angle_deg)
    u = np.array([np.sin(a), np.cos(a)])
    v = np.array([np.cos(a), -np.sin(a)])
    n = np.arange(-60, 61)
    i, j = np.meshgrid(n, n, indexing='ij')
    c = (size - 1) / 2.0
    return c + period_px * (i.ravel()[:, None] * u + j.ravel()[:, None] * v)


def _check_params(params, angle_deg, period_px):
    truth = np.mod(np.radians([angle_deg, angle_deg + 90.0]), np.pi)
    d = np.abs(np.angle(np.exp(2j * (np.asarray(params.angles)[:, None] - truth[None])))) / 2
    assert np.all(d.min(axis=1) < np.radians(2.0)), (np.degrees(params.angles), angle_deg)
    assert np.allclose(params.spacing_px, period_px, rtol=0.03), (params.spacing_px, period_px)


# (angle °, pixel mm, period mm): angles over 0–180°, periods 3.5–8 px.
CASES = [
    (0.0, 2.0, 7.0),
    (17.0, 1.25, 10.0),
    (45.0, 1.4, 8.0),
    (63.0, 1.0, 5.0),
    (90.0, 1.6, 7.0),
    (112.0, 1.0, 8.0),
    (135.0, 1.8, 7.0),
    (158.0, 1.2, 6.0),
    (70.0, 1.9, 10.0),
]  # a 9 mm wall is < 1 period across on the LA: the hardest here


@pytest.mark.parametrize(
    'background_m0', [0.0, 0.35], ids=['only-heart-tagged', 'tagged-surroundings']
)
@pytest.mark.parametrize('angle_deg,pixel_mm,period_mm', CASES)
def test_grid_estimate_and_intersections_any_angle_and_period(
    angle_deg, pixel_mm, period_mm, background_m0
):
    period_px = period_mm / pixel_mm
    truth = None
    for view, (img, mask, size) in zip(
        ('SA', 'LA'), _ed_frames(angle_deg, pixel_mm, period_mm, background_m0)
    ):
        # The estimate alone, and the scale-free claim: ×1000 or ×0.001 gives the same grid.
        params = estimate_grid(img, mask)
        _check_params(params, angle_deg, period_px)
        for scale in (1e3, 1e-3):
            p2 = estimate_grid(img * scale, mask)
            assert np.allclose(np.sort(p2.angles), np.sort(params.angles)) and np.allclose(
                np.sort(p2.spacing_px), np.sort(params.spacing_px)
            )
        det = detect_intersections(img, mask=mask)
        assert det.ok, (view, det.reason)
        _check_params(det.params, angle_deg, period_px)
        truth = _true_intersections(angle_deg, period_px, size)
        d, _ = cKDTree(truth).query(det.pixel_rc)
        # Inside a real (noisy, partial-volume) wall: sub-pixel, and nothing spurious. A wall less
        # than a period thick truncates the pattern around every point: 6 % of a period there.
        tol = max(0.25, 0.06 * period_px)
        assert np.median(d) < tol and np.mean(d < 0.5 * period_px / 2) > 0.9, (view, np.median(d))
        # Found at least half of the true intersections whose pixel lies in the wall.
        q = np.rint(truth).astype(int)
        inb = np.all((q >= 0) & (q < size), axis=1)
        in_wall = int(mask[q[inb, 0], q[inb, 1]].sum())
        assert len(det) >= 0.5 * in_wall, (view, len(det), in_wall)


def test_grid_estimate_picks_the_grid_not_its_cross_terms():
    """
    Check that a 45° grid's cross terms do not replace the grid in the estimate.

    A 45° grid's cross terms (k1 ± k2) sit on the image axes at 1/√2 of the period; the
    estimate must return the grid itself.
    """
    img, mask, _ = _ed_frames(45.0, 1.9, 10.0, 0.35, seed=3)[0]
    _check_params(estimate_grid(img, mask), 45.0, 10.0 / 1.9)


def test_untagged_noise_has_no_grid():
    rng = np.random.default_rng(1)
    det = detect_intersections(rng.standard_normal((128, 128)) + 10.0)
    assert not det.ok and 'tag direction' in det.reason


def test_grid_estimate_bright_blood_thin_wall_long_axis():
    """
    Check the grid estimate on a dilated LV with blood brighter than the wall.

    A dilated LV (thin wall, about one period across) with blood brighter than the wall: in
    the LA view the cavity's outline out-weighs the tags in the plain spectra (a 15 mm 'grid'
    for 9 mm tags, and no intersection in the mask); the image less its running median finds it.
    """
    angle_deg, pixel_mm, period_mm = 20.0, 1.15, 9.0
    img, mask, _ = _ed_frames(angle_deg, pixel_mm, period_mm, 0.0, preset='dilated', blood_m0=1.3)[
        1
    ]
    _check_params(estimate_grid(img, mask), angle_deg, period_mm / pixel_mm)
    det = detect_intersections(img, mask=mask)
    assert det.ok and len(det) >= 6, det.reason

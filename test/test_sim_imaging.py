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

"""Image formation: slice planning, material-carried SPAMM tags, blood, noise, through-plane."""

from mlv_ros.core.sim import ImageSynthesizer, plan_slices, simulate_study, slab_profile
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
import pytest
from scipy.ndimage import map_coordinates


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=None, quick=True, seed=0)


def test_study_layout(study):
    m = study.motion
    assert len(study.slices) == 11
    assert [k for k in study.keys if k[0] == VIEW_SA] == [(VIEW_SA, i) for i in range(8)]
    assert [k for k in study.keys if k[0] == VIEW_LA] == [(VIEW_LA, i) for i in range(3)]
    assert len(study.frames) == 11 * m.num_phases == 110
    cine = study.cine(VIEW_LA, 1)
    np.testing.assert_allclose([f.trigger_time for f in cine], m.times)
    assert all(f.image.shape == (128, 128) and f.image.dtype == np.float32 for f in cine)
    assert len(set(study.series_uids.values())) == 11
    with pytest.raises(ValueError, match='no slice'):
        study.cine(VIEW_SA, 99)


def test_pixel_patient_round_trip(study):
    rng = np.random.default_rng(0)
    for g in study.geometries.values():
        rc = rng.uniform(-5, 133, size=(50, 2))
        xyz = g.pixel_to_patient(rc)
        rc2, off = g.patient_to_pixel(xyz)
        np.testing.assert_allclose(rc2, rc, atol=1e-9)
        np.testing.assert_allclose(off, 0.0, atol=1e-9)
        # out of plane: the offset is the signed distance along the normal
        rc3, off3 = g.patient_to_pixel(xyz + 2.5 * g.normal)
        np.testing.assert_allclose(rc3, rc, atol=1e-9)
        np.testing.assert_allclose(off3, 2.5, atol=1e-9)


def test_slice_plan_matches_paper_layout(study):
    f = study.motion.frame
    sa = [study.geometries[(VIEW_SA, i)] for i in range(8)]
    la = [study.geometries[(VIEW_LA, i)] for i in range(3)]
    for g in sa:
        assert abs(abs(g.normal @ f.long_axis) - 1.0) < 1e-12
    h = np.array([(g.pixel_to_patient(np.array([63.5, 63.5])) - f.apex) @ f.long_axis for g in sa])
    assert np.all(np.diff(h) < 0)  # base → apex
    np.testing.assert_allclose(np.diff(h), np.diff(h)[0], atol=1e-9)  # equally spaced
    for g in la:  # planes contain the long axis
        assert abs(g.normal @ f.long_axis) < 1e-12
        assert abs((f.apex - g.image_position) @ g.normal) < 1e-9
    angles = [np.degrees(np.arccos(abs(la[0].normal @ g.normal))) for g in la[1:]]
    np.testing.assert_allclose(angles, [60.0, 60.0], atol=1e-9)


def test_slab_profile():
    off, w = slab_profile(6.0, 5)
    assert w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(off, -off[::-1])
    assert off.max() == pytest.approx(0.6 * 6.0)
    assert w[2] == w.max()
    with pytest.raises(ValueError):
        slab_profile(6.0, 0)


def _interior(m, X, margin=1.5):
    ok = m.inside_myocardium(X)
    for d in (m.frame.long_axis, m.frame.septum, m.frame.e2):
        for sg in (-1.0, 1.0):
            ok &= m.inside_myocardium(X + sg * margin * d)
    return ok


@pytest.mark.parametrize('key', [(VIEW_SA, 2), (VIEW_SA, 5), (VIEW_LA, 0), (VIEW_LA, 2)])
def test_material_points_stay_on_tag_minima(study, key):
    """
    Check that tag intersections stay dark and squares bright through the whole cycle.

    Tag intersections and square centres laid at ED, moved by the ground truth, then sampled
    from the noiseless image: intersections stay dark, squares bright, through the whole cycle.
    ED points are taken on several planes parallel to the image (tags are planes ⟂ the image),
    so that some are inside the slab core at every phase despite through-plane motion.
    """
    m = study.motion
    im = study.preset['imaging']
    lam = im['tag_spacing_mm']
    g = study.geometries[key]
    n = study.frames[0].image.shape[0]
    c = g.pixel_to_patient(np.array([(n - 1) / 2.0, (n - 1) / 2.0]))
    k = np.arange(-12, 13)
    A, B, D = np.meshgrid(k, k, np.arange(-10.0, 10.5, 1.0), indexing='ij')

    def grid(shift):
        X = (
            c
            + np.outer((A.ravel() + shift) * lam, g.row_direction)
            + np.outer((B.ravel() + shift) * lam, g.column_direction)
            + np.outer(D.ravel(), g.normal)
        )
        return X[_interior(m, X)]

    X_int, X_sq = grid(0.0), grid(0.5)
    cine = study.cine(*key)
    contrast_moved, contrast_static = [], []
    for p in range(m.num_phases):
        E = np.exp(-m.times[p] / im['t1_s'])
        vals = []
        for X, moved in ((X_int, True), (X_sq, True), (X_int, False), (X_sq, False)):
            x = m.position(X, p) if moved else X
            rc, off = g.patient_to_pixel(x)
            core = np.abs(off) < 0.75
            assert core.sum() >= 5, (key, p)
            vals.append(map_coordinates(cine[p].image, rc[core].T, order=1))
        # every tracked intersection is darker than the median tracked square centre
        assert np.all(vals[0] < np.median(vals[1])), (key, p)
        contrast_moved.append((vals[1].mean() - vals[0].mean()) / E)
        contrast_static.append((vals[3].mean() - vals[2].mean()) / E)
    # Ideal contrast is E·M_myo; slab and PSF blur keep ≥ 60 % of it at every phase.
    assert min(contrast_moved) > 0.6
    # Negative control: ignoring the motion loses the tags around end-systole.
    assert min(contrast_static) < 0.3


def test_blood_untagged_and_background(study):
    m = study.motion
    im = study.preset['imaging']
    g = study.geometries[(VIEW_SA, 3)]
    rc, _ = g.patient_to_pixel(m.frame.apex + 0.5 * m.length * m.frame.long_axis)
    r, c = np.round(rc).astype(int)
    for f in study.cine(VIEW_SA, 3):
        patch = f.image[r - 3:r + 4, c - 3:c + 4]
        np.testing.assert_allclose(patch, im['blood_m0'], atol=1e-4)  # no tag modulation


def test_ed_mask_area_matches_geometry(study):
    m = study.motion
    for i in (2, 4):
        g = study.geometries[(VIEW_SA, i)]
        z = (g.pixel_to_patient(np.array([63.5, 63.5])) - m.frame.apex) @ m.frame.long_axis
        area = np.pi * (m.epi_radius(z) ** 2 - m.endo_radius(z) ** 2)
        measured = study.ed_masks[(VIEW_SA, i)].sum() * g.row_spacing * g.column_spacing
        assert measured == pytest.approx(area, rel=0.05)


def test_through_plane_motion_is_real(study):
    """The basal slice sees different material at ES: its ED level is higher than the plane."""
    m = study.motion
    sl = study.slices[0]
    syn = ImageSynthesizer(m, sl, 128, study.preset['imaging'], subplanes=1)
    pts = syn.base
    X = m.inverse(pts, m.es_phase)
    dz = (X - pts) @ m.frame.long_axis
    z_plane = (pts[0] - m.frame.apex) @ m.frame.long_axis
    lam = 1.0 - m.eps  # normal preset: z' = λ z, so the ED level is z / λ
    np.testing.assert_allclose(dz, z_plane * (1.0 / lam - 1.0), rtol=1e-9)
    myo_ed, _ = syn.tissue_fractions(0)
    myo_es, _ = syn.tissue_fractions(m.es_phase)
    assert np.abs(myo_es - myo_ed).sum() > 50  # pixels' worth of myocardium changed


def test_rician_noise_and_determinism():
    from mlv_ros.core.sim import load_preset, make_motion

    p = load_preset('normal')
    m = make_motion(p)
    sl = plan_slices(m, p['imaging'], 256)[3]
    syn = ImageSynthesizer(m, sl, 256, p['imaging'], subplanes=1)
    img = syn.render(0, 0.0, 20.0, np.random.default_rng(5))
    air = img[:12, :12]  # corners lie outside the body sphere: pure Rayleigh noise
    sigma = 1.0 / 20.0
    assert air.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), rel=0.1)
    np.testing.assert_array_equal(img, syn.render(0, 0.0, 20.0, np.random.default_rng(5)))
    assert not np.array_equal(img, syn.render(0, 0.0, 20.0, np.random.default_rng(6)))
    assert np.all(syn.render(0, 0.0, None, None) >= 0)
    with pytest.raises(ValueError, match='snr'):
        syn.render(0, 0.0, -1.0, np.random.default_rng(0))


def test_presets_simulate(tmp_path):
    for name in ('hypertrophic', 'dilated', 'infarct', 'cylinder'):
        s = simulate_study(name, snr=10.0, size=64, num_phases=3, subplanes=1)
        assert len(s.frames) == 33
        assert all(np.isfinite(f.image).all() for f in s.frames)
        assert any(mask.any() for mask in s.ed_masks.values())

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
ED segmentation next to a bright right ventricle (real studies always have one).

Drawn protocols with the RV forced on and bright blood (1.26-1.28 x myocardium): the RV's blood
crescent beside the septum has an outline whose spectrum, falling off as 1/frequency, used to
out-weigh the tags at the long-period end of the search band, so the tag energy was built at a
wrong frequency and the LA horseshoes failed (seed 2002 LA Dice 0.36, 2004 both LA views
failed). Scored against the simulator's ED myocardium (tissue fraction >= 0.5) around the true
long axis.
"""

from mlv_ros.core.registration import segment as seg
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices
from mlv_ros.core.sim.motion import make_motion
from mlv_ros.core.sim.protocol import draw_protocol, protocol_preset
from mlv_ros.core.types import VIEW_SA
import numpy as np
import pytest

#: As test_segment_protocols: every slice segmented, Dice >= 0.8 SA and >= 0.75 LA.
MIN_DICE = {'SA': 0.80, 'LA': 0.75}


@pytest.mark.parametrize('seed', [2002, 2004])
def test_bright_rv_beside_the_lv(seed):
    p = draw_protocol(seed, {'right_ventricle': True})
    assert p['right_ventricle'] and p['blood_m0'] > 1.2
    pre = protocol_preset(p)
    m = make_motion(pre)
    im, f = pre['imaging'], m.frame
    rng = np.random.default_rng(0)
    mid = f.apex + 0.55 * m.length * f.long_axis  # a long-axis point inside the cavity
    scored = {'SA': 0, 'LA': 0}
    for s in plan_slices(m, im):
        if s.view == VIEW_SA and s.index % 3:  # every third SA slice keeps it short
            continue
        syn = ImageSynthesizer(m, s, im['size'], im, subplanes=1)
        img = syn.render(0, 0.0, im['snr'], rng)
        truth = syn.tissue_fractions(0)[0] >= 0.5
        g = s.geometry
        if s.view == VIEW_SA:
            x = (
                f.apex
                + ((g.pixel_to_patient(np.zeros(2))[0] - f.apex) @ g.normal)
                / (f.long_axis @ g.normal)
                * f.long_axis
            )
            out, view = seg.segment_sa(img, g.patient_to_pixel(x)[0], g.row_spacing), 'SA'
        else:
            ax = np.array([f.long_axis @ g.column_direction, f.long_axis @ g.row_direction])
            out, view = seg.segment_la(img, g.patient_to_pixel(mid)[0], ax, g.row_spacing), 'LA'
        assert out.ok, f'{view} {s.index}: {out.reason}'
        d = seg.dice(out.mask, truth)
        assert d >= MIN_DICE[view], f'{view} {s.index}: Dice {d:.3f}'
        scored[view] += 1
    assert scored['SA'] >= 2 and scored['LA'] >= 2


def test_candidate_features_agree_without_a_bright_pool():
    """
    Check that on a grid alone the plain and whitened spectral estimates agree.

    A grid alone: the plain and the whitened spectral estimates agree (one candidate), at the
    grid's period and angle.
    """
    n, lam, ang = 128, 6.0, np.radians(30.0)
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    k1 = np.array([np.sin(ang), np.cos(ang)]) / lam
    k2 = np.array([np.cos(ang), -np.sin(ang)]) / lam
    img = (1.0 + np.cos(2 * np.pi * (k1[0] * rr + k1[1] * cc))) * (
        1.0 + np.cos(2 * np.pi * (k2[0] * rr + k2[1] * cc))
    )
    img += np.random.default_rng(1).normal(0.0, 0.05, img.shape)
    feats = seg.candidate_features(img)
    assert len(feats) == 1
    assert feats[0].wavelength_px == pytest.approx(lam, rel=0.03)


def _ring_beside_a_pool(seed: int, rv: bool):
    """
    Return a thin tagged SA wall around bright blood, optionally beside an RV-like crescent.

    A 3.7 px wall (endocardium 18 px, epicardium 21.7 px) under a 5.34 px grid at 23° (1009's
    wall and grid at 1.87 mm pixels), blood at 1.17 × myocardium, SNR 11, dark surroundings. The
    RV: untagged blood as bright as the LV's filling a 16 px disk 14 px to the left of the LV
    centre outside the LV (a crescent up to 8 px deep beside the septum), closed by a 1.6 px
    tagged free wall.
    """
    n = 128
    rr, cc = np.mgrid[0:n, 0:n].astype(float)
    c = np.array([n / 2 + 0.3, n / 2 - 0.2])
    r = np.hypot(rr - c[0], cc - c[1])
    t, lam = np.radians(23.0), 5.34
    kv = np.array([[np.sin(t), np.cos(t)], [-np.cos(t), np.sin(t)]]) / lam
    tags = np.prod([0.5 + 0.5 * np.cos(2 * np.pi * (k[0] * rr + k[1] * cc)) for k in kv], axis=0)
    wall = (r >= 18.0) & (r <= 21.7)
    img = np.where(r < 18.0, 1.17, 0.0) + np.where(wall, tags, 0.0)
    if rv:
        d = np.hypot(rr - c[0], cc - c[1] + 14.0)
        img += np.where((d <= 16.0) & (r > 21.7), 1.17, 0.0)
        img += np.where((d > 16.0) & (d <= 17.6) & (r > 21.7) & (cc < c[1]), tags, 0.0)
    img += np.random.default_rng(seed).normal(0.0, 1.0 / 11.0, img.shape)
    return img, c, wall, kv


def test_each_ray_has_its_own_outside_level():
    """
    Check that the RV's blood beside the septum does not thicken the wall found.

    What lies outside the LV differs around it: the RV's bright untagged blood on the septal
    side, dark tissue elsewhere. With one outside level for all rays, the wall fit pulled the
    septal epicardium into the RV pool and biased the plateau shared by all rays (mean Dice
    0.71, mean epicardium 1.6 px out, over these four noise draws; 0.93 without the RV). Each
    ray now takes its own outside level from just beyond its wall. The tag grid is given, so
    only the wall fit is tested.
    """
    dice = {}
    for rv in (False, True):
        d, epi_bias = [], []
        for seed in range(4):
            img, c, wall, kv = _ring_beside_a_pool(seed, rv)
            out = seg.segment_sa(img, c, 1.0, features=seg.tag_features(img, kv))
            assert out.ok, out.reason
            d.append(seg.dice(out.mask, wall))
            epi_bias.append(float(np.mean(out.epi)) - 21.7)
        dice[rv] = float(np.mean(d))
        assert abs(np.mean(epi_bias)) < 1.3, f'RV {rv}: epicardium {np.mean(epi_bias):+.2f} px'
    assert dice[False] >= 0.9
    assert dice[True] >= 0.75, f'Dice beside the RV {dice[True]:.3f}'

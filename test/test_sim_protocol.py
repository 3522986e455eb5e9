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
Randomised acquisition protocols: draws, CLI options and DICOM read-back.

Randomised acquisition protocols: draws stay in their documented ranges and vary,
``--random``/``--protocol``, and drawn studies written to DICOM read back right (slice counts, SA
order by position, geometry as in the ground truth, pixels within the stored quantisation, the
tag grid at the drawn angle and period).
"""

import json
import math
from pathlib import Path

from mlv_ros.cli import main
from mlv_ros.core.io import (
    load_groundtruth,
    motion_from_groundtruth,
    read_dicom_dir,
    write_groundtruth,
    write_study_dicom,
)
from mlv_ros.core.sim import load_preset, simulate_study
from mlv_ros.core.sim.protocol import (
    BASE_SIDE,
    complete_protocol,
    default_protocol,
    dicom_options,
    draw_protocol,
    ITEMS,
    load_protocol,
    protocol_preset,
    SHAPES,
)
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
import pydicom
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SMALL = {'size': 128, 'num_phases': 3}  # accepted (not drawn) values: quick studies


@pytest.fixture(scope='module')
def draws():
    return [draw_protocol(s) for s in range(50)]


def _angle_deg(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return math.degrees(math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def test_draws_stay_in_documented_ranges(draws):
    for p in draws:
        assert list(p) == list(ITEMS)
        shape = load_preset(p['shape'])
        assert p['shape'] in SHAPES
        assert np.linalg.norm(p['long_axis']) == pytest.approx(1.0, abs=1e-5)
        assert _angle_deg(p['long_axis'], BASE_SIDE) <= 40.0 + 1e-3
        for axis in np.eye(3):  # oblique: off every scanner axis
            assert 20.0 - 1e-3 <= _angle_deg(p['long_axis'], axis) <= 160.0 + 1e-3
        assert 0 <= p['septum_deg'] < 360 and 0 <= p['sa_inplane_deg'] < 360
        assert all(-50 <= c <= 50 for c in p['base_centre_mm'])
        assert 0 <= p['tag_angle_deg'] < 180
        assert 1.0 <= p['pixel_spacing_mm'] <= 2.0
        assert 5.0 <= p['tag_spacing_mm'] <= 10.0
        assert p['tag_spacing_mm'] >= 3.5 * p['pixel_spacing_mm'] - 1e-9
        assert 200.0 <= p['size'] * p['pixel_spacing_mm'] <= 380.0 and p['size'] <= 256
        assert 5.0 <= p['slice_thickness_mm'] <= 10.0
        assert 6 <= p['sa_slices'] <= 14 and 6.0 <= p['sa_spacing_mm'] <= 12.0
        # the stack lies inside the LV: below the systolic base, 10 mm above the apex
        L = shape['geometry']['length_mm']
        assert p['sa_base_gap_mm'] >= shape['motion']['base_descent_mm'] + 1.0 - 1e-9
        apex_gap = L - p['sa_base_gap_mm'] - (p['sa_slices'] - 1) * p['sa_spacing_mm']
        assert apex_gap >= 10.0 - 1e-9
        assert 2 <= p['la_planes'] <= 6
        assert len(p['la_angles_deg']) == len(p['la_flip']) == p['la_planes']
        a = p['la_angles_deg']
        assert all(0 <= x < 180 for x in a)
        assert (
            min(
                min(abs(x - y) % 180, 180 - abs(x - y) % 180)
                for i, x in enumerate(a)
                for y in a[i + 1:]
            )
            >= 20.0
        )
        assert -30 <= p['la_inplane_deg'] <= 30
        assert all(-25 <= c <= 25 for c in p['sa_fov_shift_mm'] + p['la_fov_shift_mm'])
        assert 16 <= p['num_phases'] <= 40
        assert 0.7 <= p['cycle_duration_s'] <= 1.2 and 0.8 <= p['t1_s'] <= 1.2
        assert 10.0 <= p['snr'] <= 40.0
        lo, hi = {'none': (0, 0), 'untagged': (0.05, 0.2), 'tagged': (0.2, 0.5)}[p['background']]
        assert lo <= p['background_m0'] <= hi
        assert 0.3 <= p['blood_m0'] <= 1.3
        assert p['sa_order'] in ('base_first', 'apex_first')
        assert p['sa_normal'] in ('base_to_apex', 'apex_to_base')
        assert p['dicom_bits'] in (8, 12, 16)
        assert -0.5 <= p['dicom_rescale_intercept'] <= 0.0
        if not p['dicom_rescale']:
            assert p['dicom_rescale_intercept'] == 0.0
        assert 0.5 <= p['dicom_range_fill'] <= 0.95
        assert p['dicom_sa_series'] in ('per_slice', 'single')
        assert p['dicom_instance_numbers'] in ('per_slice', 'across_slices')
        assert p['dicom_file_names'] in ('ordered', 'random')
        # plain values (YAML/JSON round trip exactly)
        assert yaml.safe_load(yaml.safe_dump(p)) == p == json.loads(json.dumps(p))


def test_every_item_varies_across_seeds(draws):
    # single tag lines are drawn only when asked (tag_lines='any'), a pair's items with them
    assert {p['tag_lines'] for p in draws} == {'grid'}
    for name in ITEMS:
        if name == 'tag_lines' or name.startswith('line_pair_'):
            continue
        values = {json.dumps(p[name]) for p in draws}
        assert len(values) >= 2, f'{name} took one value over 50 seeds: {values}'
    assert {p['shape'] for p in draws} == set(SHAPES)
    assert {p['dicom_bits'] for p in draws} == {8, 12, 16}
    assert {p['background'] for p in draws} == {'none', 'untagged', 'tagged'}
    assert len({p['sa_slices'] for p in draws}) >= 5 and len({p['la_planes'] for p in draws}) == 5


def test_draw_is_deterministic_and_items_independent():
    p = draw_protocol(5)
    assert draw_protocol(5) == p and draw_protocol(6) != p
    with pytest.raises(ValueError, match='seed'):
        draw_protocol(-1)
    # fixing an item changes no independent draw
    q = draw_protocol(5, {'tag_angle_deg': 12.5, 'snr': None, 'shape': p['shape']})
    assert q['tag_angle_deg'] == 12.5 and q['snr'] is None
    assert {k: v for k, v in q.items() if k not in ('tag_angle_deg', 'snr')} == {
        k: v for k, v in p.items() if k not in ('tag_angle_deg', 'snr')
    }
    # dependent items adapt to fixed ones
    q = draw_protocol(
        5,
        {
            'pixel_spacing_mm': 2.0,
            'la_planes': 6,
            'background': 'none',
            'dicom_rescale': False,
            'shape': 'dilated',
            'sa_spacing_mm': 6.0,
        },
    )
    assert q['tag_spacing_mm'] >= 7.0 and 100 <= q['size'] <= 190
    assert len(q['la_angles_deg']) == len(q['la_flip']) == 6
    assert q['background_m0'] == 0.0 and q['dicom_rescale_intercept'] == 0.0
    assert 6 <= q['sa_slices'] <= 14
    # a fixed count that does not fit at 6 mm gets a tighter spacing
    q = draw_protocol(5, {'shape': 'normal', 'sa_slices': 14})
    assert q['sa_slices'] == 14 and q['sa_spacing_mm'] < 6.0


@pytest.mark.parametrize(
    'fixed, key',
    [
        ({'num_phases': 1}, 'num_phases'),
        ({'tag_angle_deg': 180}, 'tag_angle_deg'),
        ({'shape': 'cylinder'}, 'shape'),
        ({'size': 128.5}, 'size'),
        ({'dicom_bits': 10}, 'dicom_bits'),
        ({'long_axis': [1, -1, -1]}, 'long_axis'),
        ({'la_angles_deg': [0, 10]}, 'la_angles_deg'),
        ({'la_planes': 3, 'la_angles_deg': [0, 60]}, 'la_angles_deg'),
        ({'tag_spacing_mm': 3.0, 'pixel_spacing_mm': 2.0}, 'tag_spacing_mm'),
        ({'background': 'none', 'background_m0': 0.3}, 'background_m0'),
        ({'dicom_rescale': False, 'dicom_rescale_intercept': -0.2}, 'dicom_rescale_intercept'),
        ({'dicom_bits': 8, 'dicom_range_fill': None}, 'dicom_range_fill'),
        ({'sa_slices': 14, 'sa_spacing_mm': 12.0, 'shape': 'normal'}, 'SA stack'),
        ({'bogus': 1}, 'bogus'),
    ],
)
def test_bad_items_are_refused_with_their_range(fixed, key):
    with pytest.raises(ValueError, match='protocol') as exc:
        draw_protocol(1, fixed)
    msg = str(exc.value)
    assert key in msg and ('allowed' in msg or 'known items' in msg) and '\n' not in msg


def test_default_protocol_is_the_preset():
    for shape in SHAPES:
        pre, ref = protocol_preset({'shape': shape}), load_preset(shape)
        assert pre['protocol'] == default_protocol(shape)
        for section in ('geometry', 'orientation', 'motion', 'expected'):
            assert pre[section] == ref[section]
        assert {k: pre['imaging'][k] for k in ref['imaging']} == ref['imaging']
    # ... and simulates the very same images (the new imaging keys default to today's protocol)
    a = simulate_study(protocol_preset({}), snr=20.0, size=48, num_phases=2, subplanes=1, seed=2)
    b = simulate_study('normal', snr=20.0, size=48, num_phases=2, subplanes=1, seed=2)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa.image, fb.image)
        np.testing.assert_array_equal(fa.geometry.image_position, fb.geometry.image_position)


def test_imaging_options_change_only_what_they_name():
    from mlv_ros.core.sim import ImageSynthesizer, make_motion, plan_slices

    pre = load_preset('normal')
    m, im = make_motion(pre), pre['imaging']
    base = plan_slices(m, im, 32)
    opt = plan_slices(
        m,
        {
            **im,
            'sa_order': 'apex_first',
            'sa_normal': 'apex_to_base',
            'la_angles_deg': [10.0, 100.0],
            'la_flip': [True, False],
            'sa_inplane_deg': 30.0,
            'sa_fov_shift_mm': [5.0, -3.0],
        },
        32,
    )
    sa0 = [s for s in base if s.view == VIEW_SA]
    sa1 = [s for s in opt if s.view == VIEW_SA]
    assert [s.level for s in sa1] == [s.level for s in sa0][::-1]  # same planes, from the apex
    f = m.frame
    for s in sa1:
        g = s.geometry
        assert g.normal @ f.long_axis == pytest.approx(1.0)  # apex → base
        assert g.row_direction @ f.septum == pytest.approx(math.cos(math.radians(30.0)))
        c = g.pixel_to_patient(np.array([15.5, 15.5])) - f.apex
        off = c - (c @ f.long_axis) * f.long_axis
        assert off @ g.row_direction == pytest.approx(
            5.0
        ) and off @ g.column_direction == pytest.approx(-3.0)
    la = [s for s in opt if s.view == VIEW_LA]
    assert [s.level for s in la] == [10.0, 100.0]
    radial = math.cos(math.radians(10.0)) * f.septum + math.sin(math.radians(10.0)) * f.e2
    assert la[0].geometry.row_direction @ radial == pytest.approx(-1.0)  # flipped
    assert la[0].geometry.normal @ la[1].geometry.normal == pytest.approx(
        0.0, abs=1e-12
    )  # 90° apart
    with pytest.raises(ValueError, match='sa_order'):
        plan_slices(m, {**im, 'sa_order': 'middle'}, 32)
    with pytest.raises(ValueError, match='la_flip'):
        plan_slices(m, {**im, 'la_flip': [True]}, 32)
    # untagged surroundings: the static background is flat, the tagged one is not
    plane = plan_slices(m, im, 128, pixel_spacing=2.0)[0]
    rr, cc = np.mgrid[:128, :128] - 63.5
    body = (np.hypot(rr, cc) > 35) & (np.hypot(rr, cc) < 55)  # 70–110 mm off the axis: no heart
    for tagged in (True, False):
        syn = ImageSynthesizer(
            m, plane, 128, {**im, 'background_tagged': tagged, 'psf_sigma_px': 0.0}, subplanes=1
        )
        img = syn.render(0, 0.0, None, None)
        assert (np.ptp(img[body]) > 0.1) == tagged
        assert img[body].max() <= im['background_m0'] + 1e-6


def test_writer_options_are_checked(tmp_path):
    st = simulate_study('normal', snr=None, size=16, num_phases=2, subplanes=1)
    for kw, word in (
        ({'bits_stored': 10}, 'bits_stored'),
        ({'sa_series': 'all'}, 'sa_series'),
        ({'rescale': False, 'rescale_intercept': -1.0}, 'rescale_intercept'),
        ({'pixel_scale': 0.0}, 'pixel_scale'),
        ({'file_names': 'x'}, 'file_names'),
    ):
        with pytest.raises(ValueError, match=word):
            write_study_dicom(st, tmp_path, **kw)


# ------------------------------------------------------------------ DICOM round trips
CASES = [  # drawn protocols, the DICOM/order items fixed where a case must cover them
    (
        11,
        {
            'dicom_bits': 8,
            'dicom_rescale': True,
            'sa_order': 'apex_first',
            'sa_normal': 'apex_to_base',
            'dicom_sa_series': 'single',
            'dicom_instance_numbers': 'across_slices',
            'dicom_file_names': 'random',
        },
    ),
    (
        12,
        {
            'dicom_bits': 12,
            'dicom_rescale': False,
            'dicom_rescale_intercept': 0.0,
            'sa_order': 'base_first',
            'sa_normal': 'apex_to_base',
            'dicom_sa_series': 'per_slice',
            'dicom_instance_numbers': 'across_slices',
            'dicom_file_names': 'random',
        },
    ),
    (
        13,
        {
            'dicom_bits': 16,
            'dicom_rescale': True,
            'sa_order': 'apex_first',
            'sa_normal': 'base_to_apex',
            'dicom_sa_series': 'single',
            'dicom_instance_numbers': 'per_slice',
            'dicom_file_names': 'ordered',
        },
    ),
    (14, {'dicom_bits': 8, 'dicom_rescale': False, 'dicom_rescale_intercept': 0.0}),
    (15, {}),
    (16, {}),
    (17, {}),
]


def _spectrum_peak(img: np.ndarray, dx: float, pad: int = 4) -> tuple[float, float]:
    """Strongest spatial frequency of a tag image: (angle from the rows mod 90°, period mm)."""
    n = img.shape[0]
    w = np.hanning(n)
    F = np.abs(np.fft.fft2((img - img.mean()) * np.outer(w, w), s=(pad * n, pad * n)))
    f = np.fft.fftfreq(pad * n)
    KR, KC = np.meshgrid(f, f, indexing='ij')  # cycles / pixel along rows (r) and columns (c)
    band = (np.hypot(KR, KC) / dx > 1 / 14.0) & (np.hypot(KR, KC) < 1 / 2.5) & (KC >= 0)
    r, c = np.unravel_index(np.argmax(np.where(band, F, 0.0)), F.shape)
    N = pad * n

    def vertex(m, p0, p1):
        return 0.5 * (m - p1) / (m - 2 * p0 + p1)

    kr = KR[r, c] + vertex(F[r - 1, c], F[r, c], F[(r + 1) % N, c]) / N
    kc = KC[r, c] + vertex(F[r, c - 1], F[r, c], F[r, (c + 1) % N]) / N
    # a row step moves along the column direction: k = (sin θ, cos θ)/period in (row, column)
    return math.degrees(math.atan2(kr, kc)) % 90.0, dx / math.hypot(kr, kc)


@pytest.mark.parametrize('seed, fixed', CASES)
def test_drawn_study_reads_back(seed, fixed, tmp_path):
    p = draw_protocol(seed, {**SMALL, **fixed})
    study = simulate_study(protocol_preset(p), snr=p['snr'], seed=seed, subplanes=1)
    opts = dicom_options(p, study, names_seed=seed)
    paths = write_study_dicom(study, tmp_path / 'dicom', **opts)
    write_groundtruth(study, tmp_path, n_points=20, extra={'protocol': p, 'dicom': opts})
    gt = load_groundtruth(tmp_path)
    n_sa, n_la, P = p['sa_slices'], p['la_planes'], p['num_phases']

    # the files say what the protocol says
    ds = pydicom.dcmread(paths[0])
    assert ds.BitsStored == p['dicom_bits'] and ds.BitsAllocated == (
        8 if p['dicom_bits'] == 8 else 16
    )
    assert ('RescaleSlope' in ds) == p['dicom_rescale']
    heads = [pydicom.dcmread(q, stop_before_pixels=True) for q in paths]
    uids = {h.SeriesInstanceUID for h in heads}
    assert len(uids) == (1 if p['dicom_sa_series'] == 'single' else n_sa) + n_la
    inst = max(int(h.InstanceNumber) for h in heads)
    if p['dicom_instance_numbers'] == 'per_slice':
        assert inst == P
    else:
        assert inst == (n_sa if p['dicom_sa_series'] == 'single' else n_sa + n_la) * P
    if p['dicom_file_names'] == 'random':
        depths = {len(q.relative_to(tmp_path / 'dicom').parts) for q in paths}
        assert depths > {2} and not any(q.name.startswith('IM_') for q in paths)

    res = read_dicom_dir(tmp_path / 'dicom')
    assert res.problems == [] and res.warnings == []
    sa = [s for s in res.series if s.view == VIEW_SA]
    la = [s for s in res.series if s.view == VIEW_LA]
    assert len(sa) == n_sa and len(la) == n_la and len(res.frames) == (n_sa + n_la) * P
    np.testing.assert_allclose(res.long_axis.direction, study.motion.frame.long_axis, atol=1e-5)

    # SA order by position (base first), whatever the file order, names and normal sign
    f = study.motion.frame
    heights = [
        (s.geometry.pixel_to_patient(np.array([63.5, 63.5])) - f.apex) @ f.long_axis for s in sa
    ]
    assert np.all(np.diff(heights) < 0)

    # geometry equal to the ground truth's; the simulated SA index follows sa_order
    def match(g):
        d = {
            k: np.abs(t.image_position - g.image_position).max() for k, t in gt.geometries.items()
        }
        k = min(d, key=d.get)
        assert d[k] < 1e-3
        t = gt.geometries[k]
        np.testing.assert_allclose(g.row_direction, t.row_direction, atol=1e-6)
        np.testing.assert_allclose(g.column_direction, t.column_direction, atol=1e-6)
        assert g.row_spacing == pytest.approx(t.row_spacing)
        assert g.slice_thickness == pytest.approx(t.slice_thickness)
        return k

    truth_key = {(s.view, s.slice_index): match(s.geometry) for s in res.series}
    for s in sa:
        k = truth_key[(s.view, s.slice_index)]
        assert k == (
            VIEW_SA,
            s.slice_index if p['sa_order'] == 'base_first' else n_sa - 1 - s.slice_index,
        )
        sign = 1.0 if p['sa_normal'] == 'apex_to_base' else -1.0
        assert s.geometry.normal @ f.long_axis == pytest.approx(sign)
    assert sorted(truth_key[(s.view, s.slice_index)] for s in la) == [
        (VIEW_LA, k) for k in range(n_la)
    ]

    # phases and pixels: the simulated float images within the stored quantisation
    truth = {(fr.view, fr.slice_index, fr.phase_index): fr for fr in study.frames}
    slope = 1.0 / opts['pixel_scale']
    for fr in res.frames:
        t = truth[(*truth_key[(fr.view, fr.slice_index)], fr.phase_index)]
        assert fr.num_phases == P and fr.trigger_time == pytest.approx(t.trigger_time, abs=1e-6)
        assert fr.cycle_duration == pytest.approx(p['cycle_duration_s'])
        if p['dicom_rescale']:
            assert fr.image.dtype == np.float32
            img = fr.image.astype(np.float64)
        else:
            assert fr.image.dtype == (np.uint8 if p['dicom_bits'] == 8 else np.uint16)
            img = fr.image * slope
        np.testing.assert_allclose(img, t.image, rtol=0, atol=0.5 * slope * (1 + 1e-3) + 1e-6)

    # the tag grid of an ED SA frame lies at the drawn angle and period (a 1-1 grid repeats
    # every 90°, so the angle is compared mod 90)
    mid = [
        fr
        for fr in res.frames
        if fr.view == VIEW_SA and fr.slice_index == n_sa // 2 and fr.phase_index == 0
    ][0]
    angle, period = _spectrum_peak(mid.image.astype(np.float64), p['pixel_spacing_mm'])
    assert abs((angle - p['tag_angle_deg'] + 45.0) % 90.0 - 45.0) < 3.0
    assert period == pytest.approx(p['tag_spacing_mm'], rel=0.03)

    # the ground truth rebuilds the exact motion
    m = motion_from_groundtruth(tmp_path)
    np.testing.assert_allclose(
        m.position(gt.material_points, P - 1), gt.trajectories[P - 1], atol=1e-4
    )
    assert gt.meta['protocol'] == p and gt.meta['preset']['protocol'] == p


# ------------------------------------------------------------------ the CLI
def _cli(*args):
    return main(
        ['simulate', *map(str, args), '--subplanes', '1', '--points', '20', '--no-progress']
    )


def test_cli_random_writes_protocol_and_reproduces(tmp_path):
    a, b = tmp_path / 'a', tmp_path / 'b'
    assert _cli('--random', 3, '--out', a, '--size', 64, '--phases', 2) == 0
    p = load_protocol(a / 'protocol.yaml')
    assert list(p) == list(ITEMS) and p == draw_protocol(3, {'size': 64, 'num_phases': 2})
    meta = json.loads((a / 'groundtruth.json').read_text())
    assert (
        meta['protocol'] == p and meta['preset']['imaging']['tag_angle_deg'] == p['tag_angle_deg']
    )
    assert meta['dicom']['bits_stored'] == p['dicom_bits']
    # the written protocol alone reproduces the study
    assert _cli('--protocol', a / 'protocol.yaml', '--seed', 3, '--out', b) == 0
    assert load_protocol(b / 'protocol.yaml') == p
    ra, rb = read_dicom_dir(a / 'dicom'), read_dicom_dir(b / 'dicom')
    assert len(ra.frames) == len(rb.frames) == (p['sa_slices'] + p['la_planes']) * 2
    for fa, fb in zip(ra.frames, rb.frames, strict=True):
        np.testing.assert_array_equal(fa.image, fb.image)
    np.testing.assert_array_equal(
        load_groundtruth(a).trajectories, load_groundtruth(b).trajectories
    )


def test_cli_protocol_fixes_items(tmp_path):
    f = tmp_path / 'fix.yaml'
    f.write_text('shape: dilated\ntag_angle_deg: 30\nnum_phases: 2\nsize: 48\nla_planes: 2\n')
    # alone: the missing items are the preset's
    assert _cli('--protocol', f, '--out', tmp_path / 'a') == 0
    p = load_protocol(tmp_path / 'a' / 'protocol.yaml')
    want = {
        **default_protocol('dilated'),
        'tag_angle_deg': 30.0,
        'num_phases': 2,
        'size': 48,
        'la_planes': 2,
        'la_angles_deg': [0.0, 90.0],
        'la_flip': [False, False],
    }
    assert p == want == complete_protocol(yaml.safe_load(f.read_text()))
    # with --random: the rest drawn, independent items as without the file
    assert _cli('--random', 9, '--protocol', f, '--out', tmp_path / 'b') == 0
    q, r = load_protocol(tmp_path / 'b' / 'protocol.yaml'), draw_protocol(9)
    assert (q['shape'], q['tag_angle_deg'], q['num_phases'], q['size'], q['la_planes']) == (
        'dilated',
        30.0,
        2,
        48,
        2,
    )
    for k in ('long_axis', 'snr', 't1_s', 'dicom_bits', 'sa_normal', 'blood_m0'):
        assert q[k] == r[k]


@pytest.mark.parametrize(
    'text, words',
    [
        ('num_phases: 500\n', ['num_phases', '2 … 200']),
        ('tag_angle_deg: -5\n', ['tag_angle_deg', '0 ≤ x < 180']),
        ('sa_order: middle_first\n', ['sa_order', 'base_first | apex_first']),
        ('pixel_spacing_mm: 2.0\ntag_spacing_mm: 3.0\n', ['tag_spacing_mm', '2 pixels']),
        ('colour: red\n', ['unknown item', 'colour']),
        ('- just\n- a list\n', ['mapping']),
        ('shape: [unclosed\n', ['not valid YAML']),
    ],
)
def test_cli_bad_protocol_is_one_line_exit_2(tmp_path, capsys, text, words):
    f = tmp_path / 'bad.yaml'
    f.write_text(text)
    for args in (('--protocol', f), ('--random', 1, '--protocol', f)):
        assert _cli(*args, '--out', tmp_path / 'o') == 2
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and 'Traceback' not in err, err
        assert all(w in err for w in words), err
    assert _cli('--protocol', tmp_path / 'missing.yaml', '--out', tmp_path / 'o') == 2
    assert 'not found' in capsys.readouterr().err
    assert not (tmp_path / 'o').exists()


def test_readme_documents_every_item():
    text = (ROOT / 'README.md').read_text(encoding='utf-8')
    for name in ITEMS:
        assert f'`{name}`' in text, name
    assert '--random' in text and '--protocol' in text


def test_single_tag_lines_item_draws_one_family():
    """
    Check ``tag_lines: single``: accepted, carried into the preset, one family of lines drawn.

    The pattern varies across the lines (along the turned row direction) and not along them;
    a grid varies along both; an unknown value is refused by the protocol, the preset and the
    pattern.
    """
    from mlv_ros.core.geometry import SliceGeometry
    from mlv_ros.core.sim.imaging import tag_pattern

    assert complete_protocol({})['tag_lines'] == 'grid'
    assert protocol_preset({'tag_lines': 'single'})['imaging']['tag_lines'] == 'single'
    with pytest.raises(ValueError, match='tag_lines'):
        complete_protocol({'tag_lines': 'dots'})
    g = SliceGeometry(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.0, 1.0, 8.0)
    t = np.linspace(0.0, 14.0, 57)
    a, b = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    centre = np.array([31.5, 31.5, 0.0])
    across = centre + 1.75 * np.array([-b, a, 0.0]) + t[:, None] * np.array([a, b, 0.0])
    along = centre + 1.75 + t[:, None] * np.array([-b, a, 0.0])
    single = [tag_pattern(p, g, (64, 64), 7.0, 30.0, 'single') for p in (across, along)]
    grid = [tag_pattern(p, g, (64, 64), 7.0, 30.0) for p in (across, along)]
    assert np.ptp(single[0]) > 0.99 and np.ptp(single[1]) < 1e-9
    assert np.ptp(grid[0]) > 0.1 and np.ptp(grid[1]) > 0.1
    with pytest.raises(ValueError, match='single'):
        tag_pattern(across, g, (64, 64), 7.0, 30.0, 'dots')
    preset = protocol_preset({})
    preset['imaging']['tag_lines'] = 'dots'
    with pytest.raises(ValueError, match='tag_lines'):
        load_preset(preset)


def test_tag_lines_any_draws_single_line_studies_from_their_own_stream():
    """
    Check ``draw_protocol(seed, tag_lines='any')``: grid, pair and single, nothing else moved.

    Every other item is the grid draw's (the kept studies and tests draw the same studies as
    before); a pair's angle (45–135°) and breath-hold shift (≤ 4 mm in-plane, ≤ 3 mm along the
    axis) are drawn, other studies keep 90° and no shift, and a fixed protocol gives the pair
    items to pairs only.
    """
    from mlv_ros.core.sim.protocol import PAIR_DEFAULTS, protocol_identity

    kinds = set()
    for seed in range(40):
        p, q = draw_protocol(seed, tag_lines='any'), draw_protocol(seed)
        kinds.add(p['tag_lines'])
        rest = [k for k in ITEMS if k != 'tag_lines' and k not in PAIR_DEFAULTS]
        assert {k: p[k] for k in rest} == {k: q[k] for k in rest}, seed
        assert {k: q[k] for k in PAIR_DEFAULTS} == PAIR_DEFAULTS
        if p['tag_lines'] == 'pair':
            assert 45.0 <= p['line_pair_angle_deg'] <= 135.0
            assert np.hypot(*p['line_pair_shift_mm']) <= 4.0 + 0.01
            assert abs(p['line_pair_through_mm']) <= 3.0
        else:
            assert {k: p[k] for k in PAIR_DEFAULTS} == PAIR_DEFAULTS
        # a grid study's UIDs do not see the pair items (studies drawn before them keep theirs)
        assert protocol_identity(q) == {k: q[k] for k in rest + ['tag_lines']}
    assert kinds == {'grid', 'pair', 'single'}
    drawn = [draw_protocol(s, tag_lines='any') for s in range(40)]
    pairs = [p for p in drawn if p['tag_lines'] == 'pair']
    assert len({p['line_pair_angle_deg'] for p in pairs}) == len(pairs) >= 5
    assert draw_protocol(3, {'tag_lines': 'pair'})['line_pair_shift_mm'] != [0.0, 0.0]
    assert complete_protocol({'tag_lines': 'pair'})['line_pair_shift_mm'] == [0.0, 0.0]
    with pytest.raises(ValueError, match='line_pair_angle_deg.*tag_lines = grid'):
        complete_protocol({'line_pair_angle_deg': 60.0})
    with pytest.raises(ValueError, match='line_pair_angle_deg'):
        complete_protocol({'tag_lines': 'pair', 'line_pair_angle_deg': 20.0})
    with pytest.raises(ValueError, match='tag_lines'):
        draw_protocol(1, tag_lines='pair')


def test_line_pair_second_series_is_turned_and_shifted(tmp_path):
    """
    Check ``mlv-ros simulate`` of a 60° pair 3 mm apart: the protocol and the second series.

    The second series' tag family lies 60° from the first's (spectral estimate within 2°), the
    DICOM geometry of the two the same (where its heart sits: ``test_tags_line_pair``).
    """
    from mlv_ros.core.tags import estimate_line_family

    (tmp_path / 'p.yaml').write_text(
        'tag_lines: pair\nline_pair_angle_deg: 60\nline_pair_shift_mm: [3.0, 0.0]\n'
        'size: 96\nnum_phases: 2\nsa_slices: 3\nla_planes: 0\n'
    )
    out = str(tmp_path / 's')
    argv = ['simulate', '--protocol', str(tmp_path / 'p.yaml'), '--out', out, '--no-progress']
    assert main([*argv, '--subplanes', '1']) == 0
    p = load_protocol(tmp_path / 's' / 'protocol.yaml')
    assert p['line_pair_angle_deg'] == 60.0 and p['line_pair_shift_mm'] == [3.0, 0.0]
    first = read_dicom_dir(tmp_path / 's' / 'dicom' / 'lines_1').frames
    second = read_dicom_dir(tmp_path / 's' / 'dicom' / 'lines_2').frames
    a, b = first[0], [f for f in second if f.slice_index == first[0].slice_index][0]
    assert a.phase_index == b.phase_index == 0
    np.testing.assert_allclose(a.geometry.image_position, b.geometry.image_position)
    px = a.geometry.row_spacing
    turn = np.degrees(
        estimate_line_family(b.image, None, px)[1] - estimate_line_family(a.image, None, px)[1]
    )
    assert min(abs(turn % 180.0 - 60.0), abs(turn % 180.0 - 120.0)) < 2.0, turn
    assert not np.array_equal(a.image, b.image)


def test_cli_tag_lines_any_draws_a_pair_and_needs_random(tmp_path, capsys):
    """
    Check ``mlv-ros simulate --random 0 --tag-lines any``: a drawn pair written as two series.

    Seed 0 draws a pair under ``any`` (a grid without it); its protocol.yaml says how it was
    drawn, and ``--tag-lines any`` without ``--random`` is one line, exit 2.
    """
    assert draw_protocol(0)['tag_lines'] == 'grid'
    out = tmp_path / 's'
    argv = ['simulate', '--random', '0', '--tag-lines', 'any', '--size', '64', '--phases', '2']
    assert main([*argv, '--subplanes', '1', '--out', str(out), '--no-progress']) == 0
    p = load_protocol(out / 'protocol.yaml')
    assert p['tag_lines'] == 'pair'
    assert p == draw_protocol(0, {'size': 64, 'num_phases': 2}, 'any')
    assert '--tag-lines any' in (out / 'protocol.yaml').read_text()
    assert {d.name for d in (out / 'dicom').iterdir()} == {'lines_1', 'lines_2'}
    assert main(['simulate', '--tag-lines', 'any', '--out', str(tmp_path / 'x')]) == 2
    err = capsys.readouterr().err
    assert '--random' in err and err.count('\n') == 1

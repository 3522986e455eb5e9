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

"""Tag evidence: the SA tag tracks' own segment Ecc against an analytic deformation."""

import math

from mlv_ros.core.analysis import aha_segments, LVFrame
from mlv_ros.core.analysis.findings import tag_override
from mlv_ros.core.analysis.tag_strain import segment_tag_strain, slice_tag_edges, TagEdges
import numpy as np
import pytest

FRAME = LVFrame(apex=(0.0, 0.0, 0.0), base=(0.0, 0.0, 80.0), reference=(1.0, 0.0, 0.0))
PERIOD = 6.0  # mm, tag period
A, B = 1.3, -10.0  # contracting wall: r' = A r + B (Err = (A² − 1) / 2 = 0.345)


def _grid(z: float, r_in: float = 20.0, r_out: float = 32.0, angle_deg: float = 20.0):
    """Return a tag grid's intersections inside the annulus, rotated, on the plane z (K, 3)."""
    k = np.arange(-8, 9) * PERIOD + 0.7
    u, v = np.meshgrid(k, k)
    a = math.radians(angle_deg)
    x = u * math.cos(a) - v * math.sin(a)
    y = u * math.sin(a) + v * math.cos(a)
    r = np.hypot(x, y)
    keep = (r >= r_in) & (r <= r_out)
    return np.stack([x[keep], y[keep], np.full(keep.sum(), z)], axis=1)


def _deform(p, still_centre_deg: float | None, still_width_deg: float = 80.0):
    """Contract the wall radially (r' = A r + B) except in a still sector (r' = r)."""
    r = np.hypot(p[:, 0], p[:, 1])
    th = np.arctan2(p[:, 1], p[:, 0])
    r_new = A * r + B
    if still_centre_deg is not None:  # the sector in the frame's angles
        ie = FRAME.inplane(p)
        th_frame = np.arctan2(ie[:, 1], ie[:, 0])
        d = np.degrees(np.angle(np.exp(1j * (th_frame - math.radians(still_centre_deg)))))
        r_new = np.where(np.abs(d) <= still_width_deg / 2, r, r_new)
    q = p.copy()
    q[:, 0], q[:, 1] = r_new * np.cos(th), r_new * np.sin(th)
    return q


def _segment_centre(segment: int, level: float) -> float:
    """Return the angle (degrees) at the middle of an AHA segment of the test frame."""
    th = np.radians(np.arange(-180.0, 180.0, 0.5))
    seg = aha_segments(np.full(th.size, level), th, FRAME.aha_origin_deg)
    return float(np.degrees(np.angle(np.mean(np.exp(1j * th[seg == segment])))))


def _expected_ecc(points, segment: int, level: float) -> float:
    """Return the analytic Ecc ((A + B / r)² − 1) / 2 averaged over the segment's edges."""
    e = slice_tag_edges(points, (0, 0, 1), FRAME.apex, FRAME.axis)
    ie = FRAME.inplane(e['midpoint'])
    seg = aha_segments(np.full(len(ie), level), np.arctan2(ie[:, 1], ie[:, 0]),
                       FRAME.aha_origin_deg)
    r = np.hypot(*ie[seg == segment].T)
    return float(np.mean(0.5 * ((A + B / r) ** 2 - 1.0)))


def test_edges_join_neighbours_only_and_their_directions_are_unit():
    ed = _grid(40.0)
    e = slice_tag_edges(ed, (0, 0, 1), FRAME.apex, FRAME.axis)
    assert len(e['length']) > 50
    # Only neighbours (λ, λ√2 apart) are edges: none spans the cavity.
    assert e['length'].max() <= 1.6 * PERIOD + 1e-9
    assert np.all(np.abs(e['cos'] ** 2 + e['sin'] ** 2 - 1.0) < 1e-9)
    # The radial component is the edge's along the line from the axis to its midpoint.
    r = e['midpoint'][:, :2] / np.hypot(*e['midpoint'][:, :2].T)[:, None]
    t = (ed[e['j']] - ed[e['i']])[:, :2] / e['length'][:, None]
    np.testing.assert_allclose(np.abs(e['sin']), np.abs(np.sum(r * t, axis=1)), atol=1e-9)


def test_a_still_sector_reads_zero_among_contracting_segments():
    level = 0.5
    still = 7
    ed = _grid(level * FRAME.length)
    now = _deform(ed, _segment_centre(still, level))
    ev = segment_tag_strain([(ed, now, (0, 0, 1))], FRAME)
    mid = np.arange(6, 12)  # segments 7–12 (index 6–11)
    assert np.all(np.isfinite(ev['ecc'][mid])) and np.all(ev['edges'][mid] >= 5)
    assert abs(ev['ecc'][still - 1]) < 0.01  # the still sector: no strain at all
    # The contracting segments away from the sector's hinges: the analytic Ecc, within 0.01,
    # although Err (+0.345) is large and the grid runs at 20° to the sector.
    for s in (9, 10, 11):
        assert ev['ecc'][s - 1] == pytest.approx(_expected_ecc(ed, s, level), abs=0.01)
    # No evidence outside the slice's ring.
    assert np.all(np.isnan(ev['ecc'][:6])) and np.all(np.isnan(ev['ecc'][12:]))


def test_uncertainty_covers_localisation_noise():
    level = 0.5
    ed = _grid(level * FRAME.length)
    rng = np.random.default_rng(3)
    errors, sigmas = [], []
    for _ in range(20):
        now = _deform(ed, None) + rng.normal(0.0, 0.3, ed.shape) * (1, 1, 0)
        noisy_ed = ed + rng.normal(0.0, 0.3, ed.shape) * (1, 1, 0)
        ev = segment_tag_strain([(noisy_ed, now, (0, 0, 1), 0.3)], FRAME)
        for s in range(7, 13):
            errors.append(ev['ecc'][s - 1] - _expected_ecc(ed, s, level))
            sigmas.append(ev['ecc_unc'][s - 1])
    z = np.abs(errors) / np.asarray(sigmas)
    assert np.mean(z <= 2.0) >= 0.9  # 2σ covers at least 90 % of the segments
    assert np.all(np.asarray(sigmas) >= 0.02)  # never below the readers' spread


def test_too_few_tracks_give_no_evidence_and_bad_input_is_refused():
    ed = _grid(40.0)[:3]
    ev = segment_tag_strain([(ed, ed, (0, 0, 1))], FRAME)
    assert np.all(np.isnan(ev['ecc'])) and ev['edges'].sum() <= 3
    with pytest.raises(ValueError, match='same shape'):
        segment_tag_strain([(ed, ed[:2], (0, 0, 1))], FRAME)
    with pytest.raises(ValueError, match='finite'):
        slice_tag_edges(ed * np.nan, (0, 0, 1), FRAME.apex, FRAME.axis)
    with pytest.raises(ValueError, match='track positions'):
        TagEdges([(ed, (0, 0, 1))], FRAME).segment_strain(ed[:2])


def test_tags_overrule_a_model_that_smooths_a_still_segment_into_line():
    classes = ['normal'] * 16 + ['indeterminate']
    classes[8] = 'akinetic'  # the model's own finding is kept whatever the tags say
    tag = np.full(17, -0.15)
    unc = np.full(17, 0.025)
    tag[16] = np.nan  # the apex cap: no tag Ecc
    tag[6] = -0.01  # segment 7: the tags see no shortening, the model reads normal
    tag[10], unc[10] = -0.03, 0.08  # segment 11: too uncertain to say how much less
    tag[2] = 0.06  # segment 3: stretching
    out, from_tags, (f, fu, ref) = tag_override(classes, tag, unc)
    assert ref == pytest.approx(-0.15)
    assert out[6] == 'akinetic' and out[10] == 'indeterminate' and out[2] == 'dyskinetic'
    assert out[8] == 'akinetic' and out[16] == 'indeterminate'
    assert from_tags == [3, 7, 11]
    assert [c for k, c in enumerate(out) if k + 1 not in (3, 7, 9, 11, 17)] == ['normal'] * 12
    # A carried (unsupported) segment is left as the model's rule has it; no evidence: nothing.
    out, from_tags, _ = tag_override(classes, tag, unc, unsupported=(7,))
    assert out[6] == 'normal' and 7 not in from_tags
    out, from_tags, _ = tag_override(classes, np.zeros(0), np.zeros(0))
    assert list(out) == classes and from_tags == []


def test_tags_tell_a_still_segment_that_bulges_and_an_unsure_stretch_sets_no_class():
    """
    Dyskinetic from the tags where the model reads still; no class from an unsure stretch.

    Segment 13 (apical: 0.6 of the median Ecc expected) the model reads akinetic, its tags
    stretch (Ecc +0.04 ± 0.022: f_tag −0.44 ± 0.24): dyskinetic. Segment 9 akinetic with tags
    that read still: kept. Segment 10 normal to the model, its tags read Ecc +0.78 ± 0.36 (a
    slipped track: 2.2σ "stretching", σ_f_tag 2.4): indeterminate, not dyskinetic. Segment 14
    akinetic with tags stretching as unsurely: kept.
    """
    classes = ['normal'] * 16 + ['indeterminate']
    classes[8] = classes[12] = classes[13] = 'akinetic'
    tag = np.full(17, -0.15)
    unc = np.full(17, 0.022)
    tag[16] = np.nan
    tag[12] = 0.04
    tag[8] = -0.005
    tag[9], unc[9] = 0.78, 0.36
    tag[13], unc[13] = 0.5, 0.2
    out, from_tags, (f, fu, _) = tag_override(classes, tag, unc)
    assert f[12] == pytest.approx(-0.444, abs=1e-3)
    assert fu[12] == pytest.approx(0.244, abs=1e-3)
    assert out[12] == 'dyskinetic' and out[8] == 'akinetic' and out[13] == 'akinetic'
    assert out[9] == 'indeterminate' and fu[9] > 0.33
    assert from_tags == [10, 13]
    assert [c for k, c in enumerate(out) if k + 1 not in (9, 10, 13, 14, 17)] == ['normal'] * 12


def test_streamed_findings_take_the_es_phase_tag_evidence():
    """The findings read the tag evidence the metrics of their ES phase carry, and say so."""
    from mlv_ros.core.analysis import PhaseMetrics, segment_findings

    def phase(index, volume, tag7):
        tag = np.full(17, -0.15)
        tag[16], tag[6] = np.nan, tag7
        return PhaseMetrics(
            phase_index=index,
            num_phases=10,
            cavity_volume_ml=volume,
            segment_err=np.full(17, 0.3),
            segment_ecc=np.full(17, -0.15),  # the model: segment 7 as its neighbours
            segment_ell=np.full(17, -0.1),
            segment_count=np.full(17, 500),
            segment_err_unc=np.full(17, 0.05),
            segment_ecc_unc=np.full(17, 0.02),
            segment_ell_unc=np.full(17, 0.02),
            segment_tag_ecc=tag,
            segment_tag_ecc_unc=np.full(17, 0.025),
        )

    f = segment_findings([phase(1, 100.0, -0.14), phase(4, 60.0, -0.005), phase(7, 80.0, -0.14)])
    assert f.es_phase == 4 and f.classes[6] == 'akinetic' and f.from_tags == [7]
    assert f.tag_function_index[6] == pytest.approx(0.005 / 0.15, abs=1e-9)
    assert f.to_dict()['segments'][6]['class_from_tags'] and f.to_dict()['from_tags'] == [7]
    # Without tag evidence (older recordings), the model's class stands.
    old = {**phase(4, 60.0, -0.005).to_dict(), 'segment_tag_ecc': [], 'segment_tag_ecc_unc': []}
    plain = segment_findings([PhaseMetrics.from_dict(old)])
    assert plain.classes[6] == 'normal' and plain.from_tags == []

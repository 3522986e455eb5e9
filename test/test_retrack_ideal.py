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
``bench/retrack.py --ideal`` against an independent Newton solve on the analytic phantom.

``bench/retrack.py --ideal``: tracked points replaced by where the truth puts them (their ED
material line crossing the image plane), checked against an independent Newton solve of the same
crossing on the analytic phantom. Also the per-segment track counts the bench reports.
"""

import json
from pathlib import Path
import sys

from mlv_ros.core.sim import simulate_study
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
from retrack import ideal_targets, segment_tracks, track_errors  # noqa: E402
from test_tracking import grid_tags, observed, tagset  # noqa: E402


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def test_ideal_targets_are_the_material_lines_crossing_the_planes(study):
    m = study.motion
    refs = grid_tags(study)
    es = int(round(m.es_phase))
    truth = observed(study, refs, es)  # Newton on each ED line, kept where it stays in the wall
    sets = {
        0: {
            k: tagset(k, g, 0, m.num_phases, refs[k], np.arange(len(refs[k])))
            for k, g in study.geometries.items()
        }
    }
    rng = np.random.default_rng(0)
    sets[es] = {}
    for k, s in truth.items():  # tracked points off by up to 3 mm, one track unknown at ED
        s.position = s.position + rng.uniform(-3.0, 3.0, s.position.shape)
        s.track_id = np.append(s.track_id[:-1], 10**6).astype(np.int32)
        sets[es][k] = s
    ideal, kept = ideal_targets(sets, m)
    assert kept == len(truth)  # the unknown track of each plane keeps its measured position
    exact = observed(study, refs, es)
    for k, s in ideal[es].items():
        err = np.linalg.norm(s.position[:-1] - exact[k].position[:-1], axis=1)
        assert err.max() < 0.05, (k, err.max())
        assert np.array_equal(s.position[-1], sets[es][k].position[-1])
    assert ideal[0] is sets[0]


def _ed_and_es(study):
    """Return the grid's ED tag sets and the truth's ES ones (``observed``), by view key."""
    m = study.motion
    refs = grid_tags(study)
    ed = {
        k: tagset(k, g, 0, m.num_phases, refs[k], np.arange(len(refs[k])))
        for k, g in study.geometries.items()
    }
    return ed, observed(study, refs, int(round(m.es_phase)))


def test_ideal_segments_move_only_the_tracks_of_those_segments(study):
    from mlv_ros.core.sim.regional import truth_segments

    m = study.motion
    es = int(round(m.es_phase))
    ed, tracked = _ed_and_es(study)
    rng = np.random.default_rng(1)
    for s in tracked.values():  # tracked points off by up to 3 mm
        s.position = s.position + rng.uniform(-3.0, 3.0, s.position.shape)
    sets = {0: ed, es: tracked}
    every, _ = ideal_targets(sets, m)
    seg = {k: dict(zip(p.track_id, truth_segments(m, p.position))) for k, p in ed.items()}
    chosen = {int(v) for d in seg.values() for v in d.values() if v % 2}
    part, _ = ideal_targets(sets, m, segments=chosen)
    moved = 0
    for k, s in part[es].items():
        inside = np.array([int(seg[k][t]) in chosen for t in s.track_id])
        assert np.array_equal(s.position[inside], every[es][k].position[inside])
        assert np.array_equal(s.position[~inside], tracked[k].position[~inside])
        moved += int(inside.sum())
    assert 0 < moved < sum(len(s) for s in tracked.values())
    with pytest.raises(ValueError, match='every_track'):
        ideal_targets(sets, m, every_track=True, segments=chosen)


def test_every_track_keeps_the_tracks_a_tracker_lost(study):
    m = study.motion
    es = int(round(m.es_phase))
    ed, tracked = _ed_and_es(study)
    for s in tracked.values():  # the tracker kept only every third track
        keep = np.arange(len(s.track_id)) % 3 == 0
        s.position, s.track_id, s.pixel_rc = s.position[keep], s.track_id[keep], s.pixel_rc[keep]
        s.confidence = s.confidence[keep]
    ideal, _ = ideal_targets({0: ed, es: tracked}, m, every_track=True)
    _, exact = _ed_and_es(study)
    for k, s in ideal[es].items():
        assert s.phase_index == es and len(s) > len(tracked[k])
        want = dict(zip(exact[k].track_id, exact[k].position))
        common = [i for i, t in enumerate(s.track_id) if t in want]
        assert len(common) >= len(exact[k]) - 1  # every track the phantom keeps in the wall
        err = np.linalg.norm(
            s.position[common] - np.array([want[s.track_id[i]] for i in common]), axis=1
        )
        assert err.max() < 0.05, (k, err.max())


def test_segment_tracks_counts_what_the_tracker_kept_in_the_abnormal_segment(study, tmp_path):
    from mlv_ros.core.sim.regional import truth_segments

    m = study.motion
    refs = grid_tags(study)
    es = int(round(m.es_phase))
    segments = [{'segment': k, 'class': 'akinetic' if k == 7 else 'normal'} for k in range(1, 18)]
    (tmp_path / 'study').mkdir()
    (tmp_path / 'study' / 'groundtruth.json').write_text(
        json.dumps({'regional': {'phase': es, 'segments': segments}})
    )
    ed, later, want = {}, {}, {}
    for k, g in study.geometries.items():
        ids = np.arange(len(refs[k]))
        ed[k] = tagset(k, g, 0, m.num_phases, refs[k], ids)
        in7 = truth_segments(m, refs[k]) == 7
        keep = ~in7 | (np.cumsum(in7) == 1)  # the tracker keeps one track of segment 7 per plane
        later[k] = tagset(k, g, es, m.num_phases, refs[k][keep], ids[keep])
        la = k[0] != 0
        want[la] = np.add(want.get(la, 0), [int(in7.sum()), int(in7.any())])
    assert want[False][0] > 3  # the grid puts SA tracks in segment 7
    out = segment_tracks(tmp_path, {0: ed, es: later}, m)
    assert out['segment_7_akinetic_tracks'] == [*want[False], *want.get(True, [0, 0])]
    assert out['sa_tracks_kept'] == {
        'akinetic_dyskinetic': round(want[False][1] / want[False][0], 2),
        'normal_segments': 1.0,
    }
    assert not any(k.startswith('segment_') and '_7_' not in k for k in out)


def test_track_errors_measure_a_known_radial_offset_and_the_tracks_kept(study):
    # Every other SA track kept at ES, each moved 0.6 mm outward along the truth's radial
    # direction (at its true position): the report reads +0.6 mm radial, 0 circumferential, in
    # every wall quarter and, signed toward mid-wall, by distance to the nearest ES border, and the
    # SA tracks kept counted; LA points left exact read 0.
    m = study.motion
    refs = grid_tags(study)
    es = int(round(m.es_phase))
    ed = {
        k: tagset(k, g, 0, m.num_phases, refs[k], np.arange(len(refs[k])))
        for k, g in study.geometries.items()
    }
    later = observed(study, refs, es)
    fr = m.frame
    n_kept = 0
    for k, pts in later.items():
        if k[0] != 0:
            continue
        keep = np.arange(len(pts.track_id)) % 2 == 0
        n_kept += int(keep.sum())
        pos, ids = pts.position[keep], pts.track_id[keep]
        _, th, _ = fr.to_local(pos)
        e_r = np.cos(th)[:, None] * fr.septum + np.sin(th)[:, None] * fr.e2
        later[k] = tagset(k, pts.geometry, es, m.num_phases, pos + 0.6 * e_r, ids)
    out = track_errors({0: ed, es: later}, m, period_mm=8.0)
    sa, la = out['sa'], out['la']
    assert out['es_phase'] == es and sa['wrong'] == 0
    assert sa['radial_mm'] == pytest.approx(0.6, abs=0.05)
    assert abs(sa['circ_mm']) <= 0.05 and sa['err_median_mm'] == pytest.approx(0.6, abs=0.05)
    for n_ed, _, radial, circ, _ in sa['quarters']:
        assert n_ed > 0 and radial == pytest.approx(0.6, abs=0.05) and abs(circ) <= 0.05
    assert sa['kept'] == n_kept and n_kept < sa['visible'] <= sa['ed']
    assert la['err_median_mm'] <= 0.05 and la['kept'] <= la['visible'] <= la['ed']
    # Split by the nearest ES border: outward is toward mid-wall from the endocardium (+0.6)
    # and away from it at the epicardium (-0.6), in every band that holds points.
    bands = out['sa_border_bands']
    for side, want in (('endo', 0.6), ('epi', -0.6)):
        held = [b for b in bands[side] if b[2]]
        assert held and all(b[3] == pytest.approx(want, abs=0.05) for b in held), (side, held)
    assert sum(b[2] for side in bands.values() for b in side) <= n_kept

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
The phase solver fed points on single families of tag lines (1-D springs, ``n nᵀ``).

A point on one family of parallel tag lines measures only the motion along the lines' normal
n: the data spring, outlier screen, attachment and twist function use ``n nᵀ`` for it instead
of the in-plane ``I − ν νᵀ`` of an intersection. Exact constraints from the analytic phantom
(material lines through the slab, as SPAMM tags are), each target moved along its line by a
random amount (what a line measures does not fix it), dense error against the ground truth.
"""

from mlv_ros.core.meshless import plane_projectors
from mlv_ros.core.sim import simulate_study
import numpy as np
import pytest
from test_tracking import grid_tags, make_tracker, observed, tagset


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def family_normal(g, angle_deg):
    """Return the ED normal of a family at ``angle_deg`` to the image rows (patient coords)."""
    a = np.radians(angle_deg)
    return np.cos(a) * g.row_direction + np.sin(a) * g.column_direction


def deformed_normal(motion, X, n0, g, phase, h=0.05):
    """
    Return the unit in-plane normal at ``phase`` of the material tag plane ⟂ ``n0`` through X.

    The tag surface's normal maps as ``F⁻ᵀ n0`` (F by central differences of the analytic motion,
    ``h`` mm); its trace in the image plane has the in-plane part of that as its normal.
    """
    F = np.stack(
        [
            (motion.position(X + h * e, phase) - motion.position(X - h * e, phase)) / (2 * h)
            for e in np.eye(3)
        ],
        axis=2,
    )
    n = np.linalg.solve(np.swapaxes(F, 1, 2), np.broadcast_to(n0, X.shape)[:, :, None])[:, :, 0]
    n -= (n @ g.normal)[:, None] * g.normal
    return n / np.linalg.norm(n, axis=1)[:, None]


def line_sets(study, refs, phase, angles, rng, slide_mm=3.0):
    """
    Return each plane's tag points as points on single tag lines, one family per entry of angles.

    ``angles``: (view, slice) → list of family angles (degrees to the image rows). A family's
    points are the ED intersections of ``refs`` (every one lies on a line of each family);
    their targets slide along the deformed line by up to ``slide_mm``, and carry its normal.
    """
    sets = {}
    grid = observed(study, refs, phase)
    for key, g in study.geometries.items():
        s = grid[key]
        X0 = refs[key][s.track_id]  # ED positions of the points observed
        pos, ids, lines = [], [], []
        for f, angle in enumerate(angles[key]):
            n = deformed_normal(study.motion, X0, family_normal(g, angle), g, phase)
            along = np.cross(g.normal, n)
            slide = rng.uniform(-slide_mm, slide_mm, len(n))[:, None] if phase else 0.0
            pos.append(s.position + slide * along)
            ids.append(s.track_id + 100000 * f)
            lines.append(n)
        pts = tagset(
            key, g, phase, study.motion.num_phases, np.concatenate(pos), np.concatenate(ids)
        )
        pts.line_normal = np.concatenate(lines)
        sets[key] = pts
    return sets


def solve_lines(study, angles, **tracker_options):
    """ED particles and the ES solution from line points of the families ``angles``."""
    m, rng = study.motion, np.random.default_rng(3)
    es = int(round(m.es_phase))
    X, tr = make_tracker(study, **tracker_options)
    refs = grid_tags(study)
    for key, s in line_sets(study, refs, 0, angles, rng).items():
        tr.set_reference(s)
    return X, tr.solve(es, line_sets(study, refs, es, angles, rng), m.num_phases)


def errors(study, X, sol):
    es = int(round(study.motion.es_phase))
    return sol.positions - study.motion.position(X, es)


def test_two_line_families_recover_the_motion_as_a_grid_does(study):
    angles = {key: [0.0, 90.0] for key in study.geometries}
    X, sol = solve_lines(study, angles, slice_following=2)
    err = np.linalg.norm(errors(study, X, sol), axis=1)
    # The grid's own test bound (test_tracking: exact in-plane tags); displacements up to ~15 mm.
    # Measured 0.25 / 0.69 mm; the same targets taken as intersections (their slide along the
    # line counted) 1.32 / 2.57 mm.
    assert np.median(err) < 0.5 and np.percentile(err, 95) < 1.5, (
        np.median(err),
        np.percentile(err, 95),
    )
    assert sol.state.residual < 0.5
    assert 'single-line' not in sol.state.verdict_reasons  # two families: a grid's data


def test_one_family_per_slice_at_alternating_angles_recovers_the_motion(study):
    angles = {key: [(0.0, 60.0, 120.0)[i % 3]] for i, key in enumerate(sorted(study.geometries))}
    X, sol = solve_lines(study, angles, slice_following=2)
    err = np.linalg.norm(errors(study, X, sol), axis=1)
    # Measured 0.64 / 1.58 mm: issue 14's per-study bound (median 1.0, p95 2.5 mm).
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.5, (
        np.median(err),
        np.percentile(err, 95),
    )


def test_one_family_alone_recovers_the_motion_along_its_normal(study):
    m = study.motion
    X, sol = solve_lines(study, {key: [0.0] for key in study.geometries}, slice_following=2)
    g = next(g for (view, _), g in study.geometries.items() if view == 0)
    err = errors(study, X, sol)
    along_n = np.abs(err @ family_normal(g, 0.0))
    es = int(round(m.es_phase))
    moved = np.abs((m.position(X, es) - X) @ family_normal(g, 0.0))
    # Measured 0.14 / 0.72 mm (the motion along n0 has a median of several mm); the other
    # in-plane component is not observed (3D error 1.7 / 5.7 mm).
    assert np.median(along_n) < 0.25 and np.percentile(along_n, 95) < 1.0, (
        np.median(along_n),
        np.percentile(along_n, 95),
        np.median(moved),
    )
    # ... and the phase says its data are 1-D (an "ok" would be 1.7 mm median off unseen).
    assert sol.state.verdict >= 1 and 'single-line tags on 11 of 11 slices (1-D data)' in (
        sol.state.verdict_reasons
    )


def test_line_projectors_are_one_dimensional_and_grid_rows_stay_in_plane():
    nu = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]])
    line = np.array([[3.0, 0.0, 1.0], [np.nan] * 3])
    P = plane_projectors(np.stack([nu, line], axis=1), 2)
    np.testing.assert_allclose(P[0], np.diag([1.0, 0.0, 0.0]), atol=1e-12)
    np.testing.assert_allclose(P[1], np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    with pytest.raises(ValueError, match='no component in its image plane'):
        plane_projectors(np.stack([nu, [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]], axis=1), 2)
    with pytest.raises(ValueError, match='finite or all NaN'):
        plane_projectors(np.stack([nu, [[1.0, np.nan, 0.0], [np.nan] * 3]], axis=1), 2)


@pytest.mark.parametrize('turn', [60.0, 45.0])
def test_a_non_90_degree_pair_recovers_the_motion_and_a_misregistered_one_degrades(study, turn):
    """
    Check two families 60° and 45° apart: within the 90° pair's bounds, two families, flagged.

    Along the direction the two families share least, a pair α apart measures with 1/sin α
    times one family's error (1.15 at 60°, 1.41 at 45°): within the 90° test's bounds here
    (measured below). Both are two families, not 1-D data (at 45° each family lies 22.5° from
    the normals' doubled-angle mean, which the 1-D check took for the dominant direction). A
    slice whose ED status says its two series disagree (the tag detector's
    ``PAIR_MISREGISTERED`` part) degrades every phase, naming the slice.
    """
    from mlv_ros.core.types import PAIR_MISREGISTERED, VIEW_SA

    m, rng = study.motion, np.random.default_rng(3)
    es = int(round(m.es_phase))
    angles = {key: [20.0, 20.0 + turn] for key in study.geometries}
    X, tr = make_tracker(study, slice_following=2)
    refs = grid_tags(study)
    note = f'{PAIR_MISREGISTERED}: the shift between its two series is unsure (test)'
    for key, s in line_sets(study, refs, 0, angles, rng).items():
        if key == (VIEW_SA, 2):
            s.status = f'3 tag-line tracks lost; {note}'
        tr.set_reference(s)
    sol = tr.solve(es, line_sets(study, refs, es, angles, rng), m.num_phases)
    err = np.linalg.norm(errors(study, X, sol), axis=1)
    # Measured 0.249 / 0.721 mm at 60°, 0.249 / 0.750 at 45° (the 90° pair: 0.251 / 0.696).
    assert np.median(err) < 0.5 and np.percentile(err, 95) < 1.5, (
        np.median(err),
        np.percentile(err, 95),
    )
    assert 'single-line' not in sol.state.verdict_reasons
    assert sol.state.verdict >= 1, sol.state.verdict_reasons
    assert f'{PAIR_MISREGISTERED} on 1 of' in sol.state.verdict_reasons
    assert 'SA 2: the shift between its two series is unsure (test)' in sol.state.verdict_reasons

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
The phase solver on its own against the analytic phantom's ground truth.

The phase solver on its own: exact in-plane tag constraints from the analytic phantom (material
lines through the slab, as SPAMM tags are), dense error against the ground truth.
"""

from mlv_ros.core.meshless import matrix_to_quat
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.tracking import MotionTracker, PhaseAssembler
from mlv_ros.core.types import TagPointSet
import numpy as np
import pytest


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def grid_tags(study, spacing_px=5.3):
    """ED tag intersections: a regular grid in every plane, inside the true myocardium."""
    m, refs = study.motion, {}
    for key, g in study.geometries.items():
        rr, cc = np.mgrid[0:128:spacing_px, 0:128:spacing_px]
        P = g.pixel_to_patient(np.stack([rr.ravel(), cc.ravel()], 1))
        refs[key] = P[m.inside_myocardium(P)]
    return refs


def tagset(key, g, phase, num_phases, pos, ids):
    return TagPointSet(
        view=key[0],
        slice_index=key[1],
        phase_index=phase,
        num_phases=num_phases,
        geometry=g,
        pixel_rc=g.patient_to_pixel(pos)[0],
        position=pos,
        track_id=ids.astype(np.int32),
        confidence=np.ones(len(ids), np.float32),
        num_sa_slices=8,
        num_la_slices=3,
    )


def observed(study, refs, phase):
    """
    Return where each ED tag line crosses its (fixed) plane at ``phase``.

    Where each ED tag line crosses its (fixed) plane at ``phase``: the material point
    p0 + s n that the true motion brings back into the plane.
    """
    m, sets = study.motion, {}
    for key, g in study.geometries.items():
        P, n = refs[key], study.geometries[key].normal
        s = np.zeros(len(P))
        for _ in range(6):  # Newton on the signed distance to the plane
            x0 = m.position(P + s[:, None] * n, phase)
            x1 = m.position(P + (s[:, None] + 0.5) * n, phase)
            s -= ((x0 - g.image_position) @ n) / (((x1 - x0) @ n) / 0.5)
        X = P + s[:, None] * n
        ok = m.inside_myocardium(X)
        sets[key] = tagset(
            key, g, phase, m.num_phases, m.position(X[ok], phase), np.flatnonzero(ok)
        )
    return sets


def make_tracker(study, n=2000, **kw):
    m = study.motion
    X = m.sample_myocardium(n, seed=1)
    fr = m.frame
    R = np.stack([fr.septum, np.cross(fr.long_axis, fr.septum), fr.long_axis], axis=1)
    return X, MotionTracker(X, X.mean(0), matrix_to_quat(R), **kw)


def referenced_tracker(study, **tracker_options):
    """``(X, tracker, refs)``: a tracker with every plane's ED grid tags as its references."""
    m = study.motion
    X, tr = make_tracker(study, **tracker_options)
    refs = grid_tags(study)
    for key, g in study.geometries.items():
        tr.set_reference(tagset(key, g, 0, m.num_phases, refs[key], np.arange(len(refs[key]))))
    return X, tr, refs


def slip(study, sets, fraction, rng):
    """Move about ``fraction`` of each set's tracks by one tag period (8 mm) along its rows."""
    for key, s in sets.items():
        slipped = rng.random(len(s.track_id)) < fraction
        s.position = s.position + slipped[:, None] * 8.0 * study.geometries[key].row_direction
    return sets


def solve_es(study, **tracker_options):
    """ED particles and the solution at ES from exact in-plane tags."""
    m = study.motion
    X, tr, refs = referenced_tracker(study, **tracker_options)
    es = int(round(m.es_phase))
    return X, tr.solve(es, observed(study, refs, es), m.num_phases)


def es_error(study, slice_following):
    X, sol = solve_es(study, slice_following=slice_following)
    return np.linalg.norm(
        sol.positions - study.motion.position(X, int(round(study.motion.es_phase))), axis=1
    ), sol


def test_dense_motion_at_end_systole_from_exact_in_plane_tags(study):
    err, sol = es_error(study, slice_following=2)
    # Truth: displacements up to ~15 mm (base descent 12 mm, twist 10°, 40 % thickening).
    assert np.median(err) < 0.5 and np.percentile(err, 95) < 1.5, (
        np.median(err),
        np.percentile(err, 95),
    )
    assert sol.state.residual < 0.5
    assert np.all(np.isfinite(sol.strain))


def test_slice_following_is_what_handles_through_plane_motion(study):
    with_follow, _ = es_error(study, slice_following=2)
    without, _ = es_error(study, slice_following=0)
    assert np.median(with_follow) < 0.85 * np.median(without)


def test_no_usable_constraint_is_a_clear_error(study):
    m = study.motion
    _, tr = make_tracker(study, n=500)
    key, g = next(iter(study.geometries.items()))
    with pytest.raises(ValueError, match='no tag point matches an ED reference'):
        tr.solve(
            1,
            {key: tagset(key, g, 1, m.num_phases, np.zeros((1, 3)), np.array([0]))},
            m.num_phases,
        )
    far = g.image_position + 500.0  # far outside the heart
    assert tr.set_reference(tagset(key, g, 0, m.num_phases, far[None], np.array([0]))) == 0


def test_phase_assembler_completeness_and_duplicates(study):
    m = study.motion
    asm = PhaseAssembler()
    keys = list(study.geometries)
    for key in keys[:-1]:
        assert (
            asm.add(
                tagset(key, study.geometries[key], 3, m.num_phases, np.zeros((0, 3)), np.array([]))
            )
            is False
        )
    assert asm.expected_slices == 11 and not asm.complete(3)
    assert asm.missing(3, keys) == [keys[-1]]
    assert asm.add(
        tagset(keys[0], study.geometries[keys[0]], 3, m.num_phases, np.zeros((0, 3)), np.array([]))
    )
    assert asm.duplicates == 1
    asm.add(
        tagset(
            keys[-1], study.geometries[keys[-1]], 3, m.num_phases, np.zeros((0, 3)), np.array([])
        )
    )
    assert asm.complete(3) and len(asm.sets(3)) == 11


def apical_twist_error(study, twist_knots):
    """Twist error (degrees) per level at ES, apex first, with exact in-plane tags."""
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import lv_frame_axes

    m = study.motion
    X, sol = solve_es(study, twist_knots=twist_knots)
    x, es = sol.positions, int(round(m.es_phase))
    fr = m.frame
    R = np.stack([fr.septum, np.cross(fr.long_axis, fr.septum), fr.long_axis], axis=1)
    analyzer = LVAnalyzer(X, LVFrame(*lv_frame_axes(X, matrix_to_quat(R))))
    got, true = analyzer.phase(x), analyzer.phase(m.position(X, es))
    return got.twist_deg - true.twist_deg


def test_twist_function_extrapolates_below_the_last_sa_slice(study):
    # Below the last SA slice only LA planes see the wall, and they do not measure circumferential
    # motion: the twist there comes from the twist function of height, not from the elasticity.
    tau_only = apical_twist_error(study, twist_knots=0)
    function = apical_twist_error(study, twist_knots=11)
    print(
        'ES twist error per level, apex first; τ only:',
        np.round(tau_only, 2),
        'twist function:',
        np.round(function, 2),
    )
    assert np.max(np.abs(function)) < 0.5, function
    assert abs(function[0]) < 0.5 * abs(tau_only[0]), (function[0], tau_only[0])


def sparse_sa_solve(study, sa_slices, **tracker_options):
    """Solve ES from the LA and the given SA slices; return (tracker, 3D error per particle)."""
    m = study.motion
    X, tr = make_tracker(study, n=1000, **tracker_options)
    refs = grid_tags(study)
    keep = [k for k in study.geometries if k[0] == 1 or k[1] in sa_slices]
    for key in keep:
        tr.set_reference(
            tagset(
                key, study.geometries[key], 0, m.num_phases, refs[key], np.arange(len(refs[key]))
            )
        )
    es = int(round(m.es_phase))
    sol = tr.solve(
        es, {k: v for k, v in observed(study, refs, es).items() if k in keep}, m.num_phases
    )
    return tr, np.linalg.norm(sol.positions - m.position(X, es), axis=1)


def test_twist_function_needs_enough_sa_slices(study):
    # From three SA slices an apical twist extrapolated from their gradient is noise times a lever
    # (unguarded, 60° and a 10 mm p95 error): the function stays off, the solve
    # is the τ-only one. From four spread slices it is fitted and does no harm.
    few, few_err = sparse_sa_solve(study, {1, 3, 5})
    _, tau_err = sparse_sa_solve(study, {1, 3, 5}, twist_knots=0)
    assert few.twist_coefficients.size == 0 and np.array_equal(few_err, tau_err)
    spread, spread_err = sparse_sa_solve(study, {1, 3, 5, 7})
    _, tau_err = sparse_sa_solve(study, {1, 3, 5, 7}, twist_knots=0)
    assert spread.twist_coefficients.size == 11
    assert np.percentile(spread_err, 95) < np.percentile(tau_err, 95) + 0.1, (
        np.percentile(spread_err, 95),
        np.percentile(tau_err, 95),
    )


def linear_twist_study(apex_deg=10.0, base_deg=-3.0, zero_level=None):
    """
    Return the normal preset with a twist linear in height, its motion and planes.

    Apex +10°, base −3° at ES (Young & Cowan 2012's normal values) put the zero-rotation level at
    10/13 of the height, where the three points the simulator interpolates lie on one line. No
    image is rendered: the tags are exact (:func:`observed`). Another ``zero_level`` bends the
    profile (a monotone PCHIP through the three points): below 10/13 its gradient steepens
    toward the apex, above it flattens there.
    """
    from types import SimpleNamespace

    from mlv_ros.core.sim.imaging import plan_slices
    from mlv_ros.core.sim.motion import LVMotion
    from mlv_ros.core.sim.presets import load_preset

    p = load_preset('normal')
    p['motion'].update(
        twist_apex_deg=apex_deg,
        twist_base_deg=base_deg,
        twist_zero_level=apex_deg / (apex_deg - base_deg) if zero_level is None else zero_level,
        num_phases=12,
    )
    motion = LVMotion(p)
    planes = plan_slices(motion, p['imaging'], 128)
    geometries = {(s.view, s.index): s.geometry for s in planes}
    return SimpleNamespace(motion=motion, geometries=geometries)


def stack_twist_error(lowest_level, edit_es=None, profile=None, **tracker_options):
    """
    Return the ES twist error per level (apex first) and the truth's twist, in degrees.

    The linear-twist study (:func:`linear_twist_study`, or the one its keywords ``profile`` give)
    from exact tags on every LA view and the SA slices above ``lowest_level`` of the height;
    ``edit_es(sets, key, study)`` may change the ES tag points of the lowest of those SA slices
    (``key``) in place.
    """
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import lv_frame_axes

    study = linear_twist_study(**(profile or {}))
    m = study.motion
    fr = m.frame
    level = {
        k: float((g.image_position - fr.apex) @ fr.long_axis) / m.length
        for k, g in study.geometries.items()
    }
    keep = [k for k in study.geometries if k[0] == 1 or level[k] > lowest_level]
    assert sum(k[0] == 0 for k in keep) >= 4 and min(level[k] for k in keep) > lowest_level
    X, tr = make_tracker(study, n=1500, **tracker_options)
    refs = grid_tags(study)
    for key in keep:
        g = study.geometries[key]
        tr.set_reference(tagset(key, g, 0, m.num_phases, refs[key], np.arange(len(refs[key]))))
    es = int(round(m.es_phase))
    sets = {k: v for k, v in observed(study, refs, es).items() if k in keep}
    if edit_es is not None:
        edit_es(sets, min((k for k in keep if k[0] == 0), key=level.get), study)
    x = tr.solve(es, sets, m.num_phases).positions
    R = np.stack([fr.septum, np.cross(fr.long_axis, fr.septum), fr.long_axis], axis=1)
    analyzer = LVAnalyzer(X, LVFrame(*lv_frame_axes(X, matrix_to_quat(R))))
    got, true = analyzer.phase(x), analyzer.phase(m.position(X, es))
    return got.twist_deg - true.twist_deg, true.twist_deg


@pytest.mark.parametrize('lowest_level', [0.3, 0.4])
def test_apical_twist_beyond_the_sa_stack_continues_the_measured_gradient(lowest_level):
    # Only the SA slices above lowest_level of the height (and every LA view): 0.3–0.4 of the LV
    # below the stack, no view sees the apex rotate. The twist there must continue the twist
    # the stack measures, linearly in height, as the truth does (apex +9° in its lowest level
    # bin). Holding the function's own end slope beyond 0.15 of the height instead turns the
    # apex the wrong way (10.4° / 11.7° off, against 1.1° / 0.8° continuing the gradient).
    err, true = stack_twist_error(lowest_level)
    print('ES twist per level, apex first: truth', np.round(true, 2), 'error', err)
    assert true[0] > 8.0  # the premise: the apex twists, linearly
    # 1.5° is a sixth of the apical twist; the measured levels themselves are within 1.1°.
    assert abs(err[0]) < 1.5 and np.max(np.abs(err)) < 1.5, err


def shift_one_sided(sets, key, study, shift_mm=1.0):
    """Keep the lowest SA slice's tracks on one side of its centre only, shifted in-plane."""
    pts, g = sets[key], study.geometries[key]
    c = pts.position.mean(axis=0)
    keep = (pts.position - c) @ g.row_direction > 0.0
    pts.position = pts.position[keep] + shift_mm * np.cross(g.normal, g.row_direction)
    pts.track_id, pts.confidence = pts.track_id[keep], pts.confidence[keep]
    pts.pixel_rc = g.patient_to_pixel(pts.position)[0]


def test_a_slice_shifted_in_its_plane_is_not_read_as_twist():
    # The apical SA slice of a stack ending at 0.3 of the height keeps only the tracks on one
    # side of its centre (as on a thin apical wall that loses tracks), all 1 mm off along the
    # tangent there: a shift of the slice in its plane, which the global stage does not model
    # (the LV's levels do not all move alike), not a rotation (the twist is the rotation about
    # each level's own centre, as the analysis measures it). Read as rotation about the long
    # axis, 1 mm at a 20–25 mm radius is 2.3–2.9° at that slice, carried to the apex by the
    # extrapolation below the stack. The global stage and the twist function alone (the local
    # stage follows the shifted points wherever the twist function puts them). A fit without each
    # slice's own shift moves the twist by 1.14° at the apex; with it, by 0.08° at most.
    def shifted(mm):
        return lambda sets, key, study: shift_one_sided(sets, key, study, mm)

    still, _ = stack_twist_error(0.3, shifted(0.0), local=False)
    moved, true = stack_twist_error(0.3, shifted(1.0), local=False)
    print('ES twist per level, apex first: truth', np.round(true, 2), 'change', moved - still)
    # 0.25° is a tenth of what the shift reads as at the slice.
    assert np.max(np.abs(moved - still)) < 0.25, moved - still


def rotate_in_plane(sets, key, study, deg):
    """Turn the slice's tag points by ``deg`` about their centre in its plane (a twist misread)."""
    pts, g = sets[key], study.geometries[key]
    tangent = np.cross(g.normal, pts.position - pts.position.mean(axis=0))
    pts.position = pts.position + np.radians(deg) * tangent
    pts.pixel_rc = g.patient_to_pixel(pts.position)[0]


def stated_apical_bound(levels: int):
    """
    Return which level bins lie below :func:`stack_twist_error`'s stack, and the stated bound.

    The stack's lowest SA slice is the first above 0.3 of the height; a bin counts as below it
    more than half a bin beyond (as ``twist_extrapolation_note`` counts it), and its bound is
    ``TWIST_EXTRAPOLATION_DEG_PER_TENTH['apical']`` per 0.1 of the length beyond, degrees.
    """
    from mlv_ros.core.analysis.frame import TWIST_EXTRAPOLATION_DEG_PER_TENTH as rate

    study = linear_twist_study()
    fr, length = study.motion.frame, study.motion.length
    lowest = min(
        level
        for level in (
            float((g.image_position - fr.apex) @ fr.long_axis) / length
            for k, g in study.geometries.items()
            if k[0] == 0
        )
        if level > 0.3
    )
    centres = (np.arange(levels) + 0.5) / levels
    beyond = centres < lowest - 0.5 / levels
    return beyond, rate['apical'] * (lowest - centres[beyond]) / 0.1


@pytest.mark.parametrize(
    'profile, misread_deg',
    [
        ({}, 1.0),
        ({'zero_level': 0.45}, 0.0),
        ({'zero_level': 0.45}, 1.0),
        ({'apex_deg': 5.0, 'base_deg': -8.0, 'zero_level': 0.5}, -1.0),
    ],
    ids=['linear-end-slice-over', 'steepening-to-apex', 'steepening-end-slice-over',
         'flattening-end-slice-under'],
)
def test_extrapolated_twist_stays_within_its_stated_uncertainty(profile, misread_deg):
    # The stack ends at 0.36 of the height, 0.31 below it lies the apical level bin's centre. The
    # truth's twist is linear or bends either way (steepening toward the apex as our simulator's
    # and Young & Cowan's normal hearts; flattening there), and the lowest slice's twist is misread
    # by 1° (a sixth of what it turns). No linear continuation knows the bend: what the run
    # says is the uncertainty of each extrapolated level, TWIST_EXTRAPOLATION_DEG_PER_TENTH per 0.1
    # of the length beyond the slices (twist_extrapolation_note); the error must stay within it
    # (measured, apical bin: 0.9° / 5.9° / 1.4° / 1.6° off, bound 7.3°; turning the apex the
    # wrong way, as holding the function's end slope did, fails it).
    def misread(sets, key, study):
        rotate_in_plane(sets, key, study, misread_deg)

    err, true = stack_twist_error(0.3, misread, profile)
    print('ES twist per level, apex first: truth', np.round(true, 2), 'error', np.round(err, 2))
    beyond, bound = stated_apical_bound(len(err))
    assert list(np.flatnonzero(beyond)) == [0, 1, 2]
    assert np.all(np.abs(err[beyond]) < bound), (err[beyond], bound)
    # Where slices are: within 1.1° with exact tags (the test above), plus the misread.
    assert np.max(np.abs(err[~beyond])) < 1.5 + abs(misread_deg), err[~beyond]


def misread_lowest_points(sets, key, study, count, mm):
    """Move the ``count`` points of the slice nearest the apex ``mm`` along its circumference."""
    pts, g = sets[key], study.geometries[key]
    fr = study.motion.frame
    lowest = np.argsort((pts.position - fr.apex) @ fr.long_axis)[:count]
    tangent = np.cross(g.normal, pts.position - pts.position.mean(axis=0))
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    pts.position[lowest] += mm * tangent[lowest]
    pts.pixel_rc = g.patient_to_pixel(pts.position)[0]


@pytest.mark.parametrize('count, mm', [(1, 4.0), (2, 2.0), (2, -2.0)])
def test_a_few_noisy_apical_points_do_not_steepen_the_extrapolation_beyond_its_uncertainty(
    count, mm
):
    # The lowest SA slice of a stack ending at 0.36 of the height: its one or two points nearest
    # the apex, which set where the extrapolation starts and the P-spline's end gradient,
    # misread along the circumference (4 mm, 2 mm: 5–10° and 2.5–5° at a 20–25 mm radius). The
    # apical gradient follows them only as far as the slices' own twists support it (study 5007
    # read its apex 11° off against a stated ±8.7°); each extrapolated level must stay within
    # the uncertainty the run states for it, at the rate alone (measured, apical bins 0.05 /
    # 0.15 / 0.25: 0.78 / 1.37 / 1.45°, 0.60 / 1.27 / 1.25°, −2.80 / −2.22 / −1.82° off, bounds
    # 7.4 / 5.0 / 2.6°). Two points 4 mm off are not within it (2.39 / 3.11 / 2.82°, with the
    # previous rule too): they move the measured end itself, which no gradient mends.
    def misread(sets, key, study):
        misread_lowest_points(sets, key, study, count, mm)

    err, true = stack_twist_error(0.3, misread)
    print('ES twist per level, apex first: truth', np.round(true, 2), 'error', np.round(err, 2))
    beyond, bound = stated_apical_bound(len(err))
    assert np.all(np.abs(err[beyond]) < bound), (err[beyond], bound)


@pytest.mark.parametrize(
    'prescreen, tracker_options',
    [(True, {}), (False, {}), (True, {'outlier_mm': 20.0}), (True, {'outlier_sigmas': 1000.0})],
    ids=['screened', 'no-prescreen', 'floor-above-the-slip', 'sigmas-above-the-slip'],
)
def test_tracks_slipped_by_a_tag_period_are_screened_out(study, prescreen, tracker_options):
    """
    Check that tracks slipping by one tag period are screened out before the fit.

    30 % of the tracks slip by one tag period (8 mm) at phase 4: screened against the previous
    phase's motion they are dropped before they drag the fit (without the screen the global fit
    follows them: median 2.4 mm). An outlier floor or a σ multiple above the slip screens none.
    """
    m = study.motion
    X, tr, refs = referenced_tracker(study, **tracker_options)
    tr.prescreen = prescreen
    rng = np.random.default_rng(0)
    for phase in range(1, 5):
        sets = observed(study, refs, phase)
        if phase == 4:
            slip(study, sets, 0.3, rng)
        sol = tr.solve(phase, sets, m.num_phases)
    err = np.linalg.norm(sol.positions - m.position(X, 4), axis=1)
    if prescreen and not tracker_options:
        assert np.median(err) < 0.5 and np.percentile(err, 95) < 1.5, (
            np.median(err),
            np.percentile(err, 95),
        )
    else:  # the premise
        assert np.median(err) > 1.0, np.median(err)


@pytest.mark.parametrize('screen_global', [False, True], ids=['motion-screen', 'global-screen'])
def test_still_sector_keeps_its_tracks_while_slipped_tracks_are_dropped(study, screen_global):
    """
    Check that a sector that does not move keeps its tracks while tracks slipped a period do not.

    The tracks of AHA segments 7 and 8 stay at their ED positions (an akinetic sector among
    contracting neighbours) and one track in ten elsewhere slips by one tag period (8 mm) from
    phase 4 on. The still tracks agree with each other and with the previous phase's motion,
    but the 12 global parameters cannot represent them: screened against the global fit as
    well, 30 % of them are dropped at ES like the slipped ones (the premise, measured);
    screened against the previous motion alone (``screen_global`` False) 2 of 43 are (at the
    sector's edge) and every slipped track the model attaches is still dropped.
    """
    from mlv_ros.core.sim.regional import truth_segments

    m = study.motion
    X, tr, refs = referenced_tracker(study)
    tr.screen_global = screen_global
    for phase in range(1, int(round(m.es_phase)) + 1):
        still, slipped = set(), set()
        sets = observed(study, refs, phase)
        for key, s in sets.items():
            ed = refs[key][s.track_id]
            sector = np.isin(truth_segments(m, ed), (7, 8))
            slip_here = ~sector & (s.track_id % 10 == 3) & (phase >= 4)
            s.position = np.where(sector[:, None], ed, s.position)
            row = study.geometries[key].row_direction
            s.position = s.position + slip_here[:, None] * 8.0 * row
            still |= {(key[0], key[1], int(t)) for t in s.track_id[sector]}
            slipped |= {(key[0], key[1], int(t)) for t in s.track_id[slip_here]}
        tr.solve(phase, sets, m.num_phases)
    screened = set(tr.screened)
    still_dropped = len(screened & still) / len(still)
    keys, rest, _, normals, _ = tr._constraints(sets)
    offsets = np.array([tr.offsets[k] for k in keys])
    attached = {k for k, ok in zip(keys, tr._attach(rest, normals, offsets)[1]) if ok}
    print('ES: still dropped', still_dropped, 'slipped attached', len(slipped & attached),
          'dropped', len(slipped & screened), 'others dropped', len(screened - still - slipped))
    assert slipped & attached and slipped & attached <= screened
    if screen_global:  # the premise
        assert still_dropped > 0.2
    else:
        assert still_dropped < 0.1
        assert len(screened - still - slipped) <= 0.02 * len(attached)


@pytest.mark.parametrize(
    'option',
    [
        {'longitudinal_weight': -1.0},
        {'longitudinal_weight': float('nan')},
        {'longitudinal_coupling': -0.1},
        {'longitudinal_coupling': float('nan')},
        {'global_prior': -0.5},
        {'global_prior': float('inf')},
        {'tag_noise_mm': -0.1},
        {'tag_noise_mm': float('nan')},
        {'coupling_plateau': 1.0},
        {'coupling_plateau': -0.1},
        {'coupling_plateau': float('nan')},
    ],
)
def test_bad_solver_weights_are_clear_errors(study, option):
    with pytest.raises(ValueError, match=next(iter(option))):
        make_tracker(study, n=300, **option)


def test_low_confidence_points_count_less(study):
    """
    Check that weighting by confidence reduces the error of displaced tag points.

    A third of the tag points is displaced by 1.5 mm in-plane (below the 3 mm outlier floor:
    the outlier screen keeps them) and reported with confidence 0.3, the rest with 0.9: weighted
    by confidence, the fit keeps less than 60 % of the error the bad points add unweighted
    (measured ~45 %).
    """
    m = study.motion
    es = int(round(m.es_phase))
    err = {}
    for case in ('exact', 'unweighted', 'weighted'):
        X, tr, refs = referenced_tracker(study, n=1000, confidence_weights=case == 'weighted')
        sets = observed(study, refs, es)
        rng = np.random.default_rng(4)
        for key, s in sets.items():
            bad = (rng.random(len(s.track_id)) < 1 / 3) & (case != 'exact')
            s.position = s.position + bad[:, None] * 1.5 * study.geometries[key].row_direction
            s.confidence = np.where(bad, 0.3, 0.9).astype(np.float32)
        sol = tr.solve(es, sets, m.num_phases)
        err[case] = float(np.median(np.linalg.norm(sol.positions - m.position(X, es), axis=1)))
    assert err['unweighted'] > err['exact'] + 0.1, err  # the premise: the bad points do pull
    assert err['weighted'] - err['exact'] < 0.6 * (err['unweighted'] - err['exact']), err


def test_noisy_slices_pull_less_than_precise_ones(study):
    """
    Check that each slice's spring follows its own measured noise: the fit follows the precise.

    Phases 1 to ES, every other slice (SA and LA) with white in-plane noise of 0.5 mm per axis
    at each phase, the others 0.03 mm. The solver measures each slice's noise from its tracks'
    second differences in time (noisy slices 0.43–0.82 mm, precise ones below 0.07 mm:
    measured, seeds 7 and 8) and weights its springs by ``(tag_noise_mm / σ)²``: the ES error
    the noise adds over exact tags falls to 27–31 % of what the same points add with every
    spring alike (measured; asserted below 50 %), and the precise slices keep full springs.
    """
    m = study.motion
    es = int(round(m.es_phase))
    refs = grid_tags(study)
    noisy = {key for key in study.geometries if key[1] % 2 == 0}
    err, noise = {}, {}
    for case, tag_noise_mm in (('exact', 0.15), ('alike', 0.0), ('own noise', 0.15)):
        # At the volume term these figures were measured with (1000 μ: exact / alike / own
        # noise 0.438 / 0.625 / 0.491 mm, 28 %). With the default 4000 the volume term carries
        # more of the motion and the weighting gains less: 0.488 / 0.639 / 0.574 mm, 57 %.
        X, tr = make_tracker(study, n=1000, tag_noise_mm=tag_noise_mm, volume_weight=1.0e3)
        for key, g in study.geometries.items():
            tr.set_reference(tagset(key, g, 0, m.num_phases, refs[key], np.arange(len(refs[key]))))
        rng = np.random.default_rng(7)
        for phase in range(1, es + 1):
            sets = observed(study, refs, phase)
            for key, s in sets.items():
                g = study.geometries[key]
                sd = (0.5 if key in noisy else 0.03) * (case != 'exact')
                e = rng.normal(0.0, sd, (len(s.track_id), 2))
                s.position = s.position + e @ np.stack([g.row_direction, g.column_direction])
            sol = tr.solve(phase, sets, m.num_phases)
        err[case] = float(np.median(np.linalg.norm(sol.positions - m.position(X, es), axis=1)))
        noise[case] = tr.noise_mm
    sigma = noise['own noise']
    assert sorted(sigma) == sorted(study.geometries)
    assert abs(np.median([sigma[k] for k in noisy]) / 0.5 - 1.0) < 0.25, sigma
    assert max(v for k, v in sigma.items() if k not in noisy) < 0.15, sigma
    assert err['alike'] > err['exact'] + 0.1, err  # the premise: the noisy points do pull
    assert err['own noise'] - err['exact'] < 0.5 * (err['alike'] - err['exact']), err


def test_second_difference_noise_recovers_white_noise_under_smooth_motion():
    """
    Check the noise estimate: white noise σ under an accelerating, rotating wall, with slips.

    60 tracks on a 40 mm slice, three phases of a motion whose acceleration is affine in position
    (up to 2.5 mm per phase², far above the noise), in-plane noise of σ = 0.25 mm per axis, and
    3 tracks slipped by a tag period (8 mm) at the latest phase. σ from 10 phases' samples is
    within 10 % of the truth (measured 0.238 mm); without the affine fit it reads 0.38 mm.
    """
    from mlv_ros.core.tracking import noise_sigma, second_difference_noise

    rng = np.random.default_rng(3)
    samples = []
    for _ in range(10):
        x0 = np.column_stack([rng.uniform(-20, 20, (60, 2)), np.zeros(60)])
        acc = np.array([[0.03, -0.04, 0.0], [0.02, 0.05, 0.0], [0.0, 0.0, 0.0]])
        t = [x0 + k * 0.5 + 0.5 * k * k * (x0 @ acc.T + [0.4, -0.3, 0.0]) for k in range(3)]
        t = [p + np.column_stack([rng.normal(0.0, 0.25, (60, 2)), np.zeros(60)]) for p in t]
        t[2][:3, 0] += 8.0
        samples.extend(second_difference_noise(t[2], t[2] - 2.0 * t[1] + t[0]))
    assert abs(noise_sigma(samples) / 0.25 - 1.0) < 0.1, noise_sigma(samples)
    assert second_difference_noise(np.zeros((5, 3)), np.zeros((5, 3))) is None  # too few tracks
    assert noise_sigma([]) is None


def test_solution_does_not_depend_on_the_order_slices_arrived_in(study):
    """
    Check that the motion does not depend on the order the slices arrive in.

    The graph hands the solver a phase's slices in the order they arrived, which depends on
    the frame order and the process layout; the motion must not. Before the solver took the
    slices in (view, slice) order, the same sets in another order gave float sums in another
    order, then another CG iteration count: 0.015 mm at one phase of a recorded study. Compared
    to the bit, over two phases (the second warm-started from the first).
    """
    m = study.motion
    solutions = []
    for order in (1, -1):
        _, tr, refs = referenced_tracker(study, n=600)
        for phase in (2, 4):
            sets = observed(study, refs, phase)
            sol = tr.solve(phase, dict(list(sets.items())[::order]), m.num_phases)
        solutions.append(sol.positions)
    assert (
        list(observed(study, refs, 2)) != list(observed(study, refs, 2))[::-1]
    )  # the premise: two orders
    np.testing.assert_array_equal(solutions[0], solutions[1])


def test_longitudinal_coupling_follows_an_akinetic_sector():
    """
    Check that the regional coupling finds the infarct phantom's akinetic sector and follows it.

    The infarct phantom's akinetic sector (levels 0.4-0.7, AHA 7): SA tags see it not
    shortening around the axis, only three LA planes see anything along it. The tag points in it
    are left outward of the smoothed motion, so the coupling's weight gathers there (measured at
    ES: mean weight 0.52 in AHA 7, 0.03 away from it and its neighbours), and there the local
    longitudinal strain follows the circumferential one: from exact tags the ES median error of
    the sector and the basal wall above it (AHA 7, 1) falls from 1.38 to 1.23 mm, the p95 from
    1.86 to 1.75 mm, the whole heart's median stays 0.39 mm (measured).

    With ``coupling_plateau`` 0.5 a flagged point gives its whole weight within half the reach:
    the sector's mean weight rises from 0.51 to 0.80 and its median error falls to 1.15 mm, the
    whole heart's median 0.385 → 0.389 mm (measured).
    """
    from mlv_ros.core.sim.regional import truth_segments

    study = simulate_study('infarct', snr=20, quick=True)
    m = study.motion
    refs = grid_tags(study)
    es = int(round(m.es_phase))
    err, weight = {}, {}
    for name, coupling, plateau in (('off', 0.0, 0.0), ('hat', 1.0, 0.0), ('plateau', 1.0, 0.5)):
        X, tr = make_tracker(
            study, n=2000, longitudinal_coupling=coupling, coupling_plateau=plateau
        )
        for key, g in study.geometries.items():
            tr.set_reference(tagset(key, g, 0, m.num_phases, refs[key], np.arange(len(refs[key]))))
        for phase in range(1, es + 1):
            sol = tr.solve(phase, observed(study, refs, phase), m.num_phases)
        err[name] = np.linalg.norm(sol.positions - m.position(X, es), axis=1)
        weight[name] = tr.coupling_weight
    seg = truth_segments(m, X)
    sector = np.isin(seg, (1, 7))
    away = ~np.isin(seg, (1, 7, 8, 12, 13))
    for key in ('hat', 'plateau'):
        assert np.mean(weight[key][seg == 7]) > 5.0 * np.mean(weight[key][away])
    # the plateau: more of the sector's weight, a smaller sector error, the rest unchanged
    assert np.mean(weight['plateau'][seg == 7]) > 1.3 * np.mean(weight['hat'][seg == 7])
    assert np.median(err['plateau'][sector]) < 0.97 * np.median(err['hat'][sector]), (
        np.median(err['hat'][sector]),
        np.median(err['plateau'][sector]),
    )
    assert np.median(err['plateau']) < np.median(err['hat']) + 0.02
    assert np.percentile(err['plateau'], 95) < np.percentile(err['hat'], 95) + 0.02
    assert np.median(err['hat'][sector]) < 0.95 * np.median(err['off'][sector]), (
        np.median(err['off'][sector]),
        np.median(err['hat'][sector]),
    )
    assert np.percentile(err['hat'], 95) < np.percentile(err['off'], 95)
    assert np.median(err['hat']) < np.median(err['off']) + 0.05


def test_track_rows_and_slice_groups_act_as_the_dicts_they_replace():
    """
    Check the per-slice arrays against dicts per track: the last of a repeated id, merges, groups.

    A dict assigned track by track keeps a repeated id's last position and, assigned again
    (a phase solved again), keeps the ids the second assignment lacks; the arrays must look up
    the same positions and report ids they do not hold as missing. Slices are grouped in the
    order each first appears, also when their keys are not contiguous.
    """
    from mlv_ros.core.tracking import _slice_groups, _track_rows

    rng = np.random.default_rng(3)
    first_ids, second_ids = np.array([7, 3, 9, 3, 12]), np.array([9, 4, 4, 20])
    first_pos, second_pos = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    expected = {}
    for ids, pos in ((first_ids, first_pos), (second_ids, second_pos)):
        for t, p in zip(ids, pos):
            expected[int(t)] = p
    rows = _track_rows(second_ids, second_pos, _track_rows(first_ids, first_pos))
    query = np.array([3, 4, 5, 7, 9, 12, 20, 21])
    hit, pos = rows.lookup(query)
    assert hit.tolist() == [int(t) in expected for t in query]
    for t, h, p in zip(query, hit, pos):
        if h:
            assert np.array_equal(p, expected[int(t)]), t
    empty_hit, _ = _track_rows(np.zeros(0, int), np.zeros((0, 3))).lookup(query)
    assert not empty_hit.any()

    keys = [(0, 2, 5), (0, 2, 6), (1, 0, 1), (0, 1, 8), (0, 2, 9)]
    groups = _slice_groups(keys)
    assert [g[0] for g in groups] == [(0, 2), (1, 0), (0, 1)]
    assert [g[1].tolist() for g in groups] == [[0, 1, 4], [2], [3]]
    assert [g[2].tolist() for g in groups] == [[5, 6, 9], [1], [8]]


def test_slice_following_step_is_exact_for_an_affine_motion(study):
    """
    Check that one slice-following step puts each material line on its plane under affine motion.

    The step's derivative is the particles' deformation gradient interpolated at the point; MLS
    reproduces an affine field and its gradient exactly, so a single Newton step lands each
    point's model position on the plane through its target (to rounding). A step without the
    gradient (derivative 1) misses by the stretch along the normal, here 25 % (0.67 mm).
    """
    X, tr = make_tracker(study, n=1500)
    centre = X.mean(axis=0)
    A = np.array([[0.95, 0.08, 0.03], [-0.06, 1.02, 0.05], [0.04, -0.03, 1.25]])
    tr.positions = (X - centre) @ A.T + centre + np.array([1.0, -2.0, 0.5])
    rng = np.random.default_rng(5)
    inner = X[np.argsort(np.linalg.norm(X - centre, axis=1))[:200]]  # deep inside the cloud
    rest = inner[rng.choice(len(inner), 40, replace=False)]
    normals = rng.normal(size=(40, 3))
    normals[:, 2] += 3.0  # mostly along the long axis (z), as SA slices are
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    offsets = rng.uniform(-1.0, 1.0, 40)
    targets = (rest + rng.uniform(-1.5, 1.5, (40, 1)) * normals - centre) @ A.T + centre
    targets += np.array([1.0, -2.0, 0.5]) + 0.7 * np.cross(normals, [1.0, 0.0, 0.0])
    inside = np.ones(40, dtype=bool)
    ctrl = tr.model.attach(rest + offsets[:, None] * normals)
    new = tr._follow_slices(offsets, rest, normals, targets, inside, ctrl)
    moved = tr.model.attach(rest + new[:, None] * normals).weights @ tr.positions
    off_plane = np.einsum('ka,ka->k', moved - targets, normals)
    before = np.einsum('ka,ka->k', ctrl.weights @ tr.positions - targets, normals)
    assert np.abs(before).max() > 0.5  # the points start off their planes
    assert np.abs(off_plane).max() < 1e-6, np.abs(off_plane).max()


def test_thick_walled_global_stage_keeps_the_wall_volume(study):
    # The global stage alone (no local stage) at ES from exact in-plane tags. The truth keeps the
    # myocardium's volume (det F = 1). The paper's affine shape scales the wall with the cavity
    # and loses ~40 % of it (measured J 0.61, median error 1.30 mm); the thick-walled shape
    # thickens the wall instead (J 0.98, 0.44 mm).
    m = study.motion
    es = int(round(m.es_phase))
    out = {}
    for thick in (False, True):
        X, tr, refs = referenced_tracker(study, local=False, global_thickening=thick)
        tr.solve(es, observed(study, refs, es), m.num_phases)
        x = tr.model.positions()
        j = np.linalg.det(np.eye(3) + tr.model.operator.gradient(x - X))
        out[thick] = np.median(j), np.median(np.linalg.norm(x - m.position(X, es), axis=1))
    assert out[False][0] < 0.8 and abs(out[True][0] - 1.0) < 0.03, out
    assert out[True][1] < 0.6 * out[False][1], out


def test_thick_walled_whole_solve_reads_radial_thickening(study):
    # The whole solve (global stage, twist function, local stage with the transmural axial
    # shear term) with the thick-walled shape, at ES from exact in-plane tags: the mean radial
    # Green strain about the long axis against the truth's (its deformation gradient; 0.417
    # here), within issue 20's must of 0.05 (measured +0.024; the paper's affine shape −0.019).
    # No axial drift either: the axial error's median within 0.1 mm (measured 0.001 mm).
    m = study.motion
    es = int(round(m.es_phase))
    X, tr, refs = referenced_tracker(study, global_thickening=True)
    tr.solve(es, observed(study, refs, es), m.num_phases)
    axis = m.frame.long_axis
    v = X - X.mean(axis=0)
    r = v - np.outer(v @ axis, axis)
    r /= np.linalg.norm(r, axis=1, keepdims=True)

    def radial(F):
        return float(np.mean(np.einsum('na,nab,nb->n', r, np.swapaxes(F, 1, 2) @ F, r) - 1) / 2)

    truth = radial(m.deformation_gradient(X, es))
    ours = radial(np.eye(3) + tr.model.operator.gradient(tr.positions - X))
    assert truth > 0.3 and abs(ours - truth) < 0.05, (ours, truth)
    assert abs(np.median((tr.positions - m.position(X, es)) @ axis)) < 0.1


def test_contraction_prior_lets_an_akinetic_sector_without_la_tags_keep_its_length():
    """
    Check that the contraction prior gives an unseen akinetic sector its own long-axis motion.

    The infarct phantom's akinetic sector (AHA 7, and the basal wall 1 above it) with every LA
    tag point in it removed, as in a study whose LA planes miss it: only SA tags see the sector,
    and they see it not contracting. Without the prior the sector shortens like its neighbours
    and the base above it descends with theirs; with it (``contraction_prior`` 1) its local
    longitudinal strain follows its own circumferential deviation from its level, at the heart's
    own Ell / Ecc ratio read near the LA tag points. The ES longitudinal error of AHA 1 and 7
    (median |error along the axis|, against the analytic truth) falls (measured 2.02 → 1.13 mm;
    whole heart p95 2.18 → 1.57 mm); the whole heart's median 3D error does not grow by more
    than 0.02 mm (measured 0.369 → 0.379 mm).
    """
    from mlv_ros.core.sim.regional import truth_segments

    study = simulate_study('infarct', snr=20, quick=True)
    m = study.motion
    refs = grid_tags(study)
    for key in refs:
        if key[0] != 0:  # LA views: none of their tag points in the sector
            refs[key] = refs[key][~np.isin(truth_segments(m, refs[key]), (1, 7))]
    es = int(round(m.es_phase))
    axis = m.frame.long_axis
    err, axial = {}, {}
    for prior in (0.0, 1.0):
        X, tr = make_tracker(study, n=2000)
        tr.contraction_prior = prior
        for key, g in study.geometries.items():
            tr.set_reference(tagset(key, g, 0, m.num_phases, refs[key], np.arange(len(refs[key]))))
        for phase in range(1, es + 1):
            sol = tr.solve(phase, observed(study, refs, phase), m.num_phases)
        d = sol.positions - m.position(X, es)
        err[prior], axial[prior] = np.linalg.norm(d, axis=1), np.abs(d @ axis)
    sector = np.isin(truth_segments(m, X), (1, 7))
    before, after = np.median(axial[0.0][sector]), np.median(axial[1.0][sector])
    assert after < 0.8 * before, (before, after)
    assert np.median(err[1.0]) < np.median(err[0.0]) + 0.02, (
        np.median(err[0.0]), np.median(err[1.0])
    )


def toward_mid_wall(study, sets, k):
    """
    Move each SA set's points toward its mid-wall radius: ρ' = ρ_m + k (ρ − ρ_m).

    The tag tracker's measured bias at end-systole (tracked minus true, radially, by ED wall
    quarter endo → epi +1.3 / +0.8 / −0.1 / −0.9 mm on a kept bench study): the tracked wall reads
    thinner than it is. ρ about the true long axis through the set's centroid, ρ_m its median.
    """
    axis = study.motion.frame.long_axis
    for key, s in sets.items():
        if key[0] != 0:
            continue
        v = s.position - s.position.mean(axis=0)
        v -= np.outer(v @ axis, axis)
        rho = np.linalg.norm(v, axis=1)
        mid = np.median(rho)
        s.position = s.position + v / rho[:, None] * ((mid + k * (rho - mid)) - rho)[:, None]
    return sets


def test_volume_term_keeps_the_wall_volume_against_tag_points_read_toward_mid_wall(study):
    # At ES, from exact in-plane tags and from the same tags read toward mid-wall (the SA wall
    # 15 % thinner than it is: ~1.5 mm of ~11 mm, the tracker's measured bias): the default
    # volume term (4000 μ) against the former 1000 μ. Measured (mean radial Green strain about
    # the long axis, truth 0.417; median det F; median 3D error mm): exact 0.398 / 0.986 / 0.341
    # → 0.413 / 0.995 / 0.346; biased 0.309 / 0.946 / 0.366 → 0.362 / 0.980 / 0.366.
    m = study.motion
    es = int(round(m.es_phase))
    axis = m.frame.long_axis

    def solve(k, **options):
        X, tr, refs = referenced_tracker(study, **options)
        tr.solve(es, toward_mid_wall(study, observed(study, refs, es), k), m.num_phases)
        v = X - X.mean(axis=0)
        r = v - np.outer(v @ axis, axis)
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        F = np.eye(3) + tr.model.operator.gradient(tr.positions - X)
        err_rr = np.mean(np.einsum('na,nab,nb->n', r, np.swapaxes(F, 1, 2) @ F, r) - 1) / 2
        T = m.deformation_gradient(X, es)
        true_rr = np.mean(np.einsum('na,nab,nb->n', r, np.swapaxes(T, 1, 2) @ T, r) - 1) / 2
        e = np.linalg.norm(tr.positions - m.position(X, es), axis=1)
        return err_rr - true_rr, np.median(np.linalg.det(F)), np.median(e)

    exact, biased = solve(1.0), solve(0.85)
    former = solve(0.85, volume_weight=1.0e3)
    assert abs(exact[0]) < 0.01 and abs(exact[1] - 1.0) < 0.01, exact
    # Read toward mid-wall: Err within issue 20's 0.05 + 0.01 and the volume within 3 %, where
    # the former weight loses 5 % and reads Err 0.11 low; the motion no worse.
    assert abs(biased[0]) < 0.06 and biased[1] > 0.97, biased
    assert former[0] < biased[0] - 0.03 and former[1] < biased[1] - 0.02, (former, biased)
    assert biased[2] < former[2] + 0.02, (biased, former)

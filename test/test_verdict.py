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
Quality verdicts (mlv_ros.core.verdict) through the real solver and analyzer.

Quality verdicts (mlv_ros.core.verdict): each threshold tripped by a study built to trip it,
and left alone by one that should pass — through the real solver and analyzer.
"""

from mlv_ros.core.analysis import LVAnalyzer
from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.analytic_lv import cylinder_shell, cylindrical_motion, oblique_frame
from mlv_ros.core.types import VIEW_SA
from mlv_ros.core.verdict import (
    DEGRADED,
    FAILED,
    FIT_SECTOR_RATIO,
    metrics_verdict,
    OK,
    phase_verdict,
    SECTOR_SHARE_DEGRADED,
    Verdict,
    weakest_sector,
    worst_fit_sector,
)
import numpy as np
import pytest
from test_tracking import observed, referenced_tracker, slip


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def solve(study, phase, edit=None, **tracker_options):
    """Return the solver's verdict at ``phase`` from exact in-plane tags, ``edit(sets)`` first."""
    m = study.motion
    _, tr, refs = referenced_tracker(study, n=1000, **tracker_options)
    sets = observed(study, refs, phase)
    if edit is not None:
        sets = edit(sets)
    return tr.solve(phase, sets, m.num_phases).state


def subset(s, k):
    """Keep only the points ``k`` (mask or indices) of tag point set ``s``, in place."""
    s.position, s.pixel_rc, s.track_id, s.confidence = (
        s.position[k],
        s.pixel_rc[k],
        s.track_id[k],
        s.confidence[k],
    )


def keep(sets, fraction, seed=0):
    rng = np.random.default_rng(seed)
    for s in sets.values():
        subset(s, rng.random(len(s.track_id)) < fraction)
    return sets


def test_a_well_tracked_phase_is_ok(study):
    state = solve(study, int(round(study.motion.es_phase)))
    assert state.verdict == OK and state.verdict_reasons == ''


def test_few_tracked_points_degrade_then_fail(study):
    es = int(round(study.motion.es_phase))
    # Every slice keeps ~20 % of its points: each still has 3+, only the total trips.
    degraded = solve(study, es, lambda s: keep(s, 0.2))
    assert degraded.verdict == DEGRADED and 'ED tag points tracked' in degraded.verdict_reasons
    failed = solve(study, es, lambda s: keep(s, 0.06))
    assert failed.verdict == FAILED and 'ED tag points tracked' in failed.verdict_reasons


def test_sa_slices_without_points_degrade_and_none_fails(study):
    es = int(round(study.motion.es_phase))
    sa = sorted(k for k in study.geometries if k[0] == VIEW_SA)

    def drop_sa(n_left):
        return lambda sets: {k: v for k, v in sets.items() if k[0] != VIEW_SA or k in sa[:n_left]}

    two = solve(study, es, drop_sa(2))  # 2 of 8 SA slices
    assert two.verdict >= DEGRADED and f'2 of {len(sa)} SA slices' in two.verdict_reasons
    none = solve(study, es, drop_sa(0))  # long-axis views only
    assert none.verdict == FAILED and 'no SA slice' in none.verdict_reasons


def test_an_end_slice_of_the_stack_without_points_degrades_an_inner_one_does_not(study):
    es = int(round(study.motion.es_phase))
    sa = sorted(k for k in study.geometries if k[0] == VIEW_SA)

    def drop(key):
        return lambda sets: {k: v for k, v in sets.items() if k != key}

    end = solve(study, es, drop(sa[-1]))  # the levels past the last one left are extrapolated
    assert end.verdict == DEGRADED and 'at the end of the stack' in end.verdict_reasons
    assert f'beyond slice {sa[-2][1]}' in end.verdict_reasons
    first = solve(study, es, drop(sa[0]))
    assert first.verdict == DEGRADED and f'beyond slice {sa[1][1]}' in first.verdict_reasons
    inner = solve(study, es, drop(sa[len(sa) // 2]))  # its neighbours bound it on both sides
    assert inner.verdict == OK, inner.verdict_reasons


def test_a_fit_that_misses_its_tracks_by_half_a_pixel_is_degraded(study):
    es = int(round(study.motion.es_phase))
    rng = np.random.default_rng(1)

    def jitter(sets):  # 1 px of independent in-plane noise per point: no smooth motion fits it
        for key, s in sets.items():
            g = study.geometries[key]
            s.position = s.position + rng.standard_normal((len(s.position), 2)) @ np.stack(
                [g.row_direction * g.row_spacing, g.column_direction * g.column_spacing]
            )
        return sets

    state = solve(study, es, jitter)
    assert state.verdict == DEGRADED and 'fit residual' in state.verdict_reasons, (
        state.verdict_reasons
    )


def test_many_outliers_degrade(study):
    m = study.motion
    _, tr, refs = referenced_tracker(study, n=1000)
    rng = np.random.default_rng(0)
    for phase in range(1, 4):
        sets = observed(study, refs, phase)
        if phase == 3:  # 30 % of the tracks slip by a tag period (8 mm): screened out, and said
            slip(study, sets, 0.3, rng)
        state = tr.solve(phase, sets, m.num_phases).state
        assert (state.verdict == OK) == (phase < 3), (phase, state.verdict_reasons)
    assert 'rejected as outliers' in state.verdict_reasons


def drop_sector(study, refs, lo_deg, hi_deg):
    """Return ``edit(sets)`` losing the SA tracks whose ED point lies in [lo, hi) degrees."""

    def edit(sets):
        for key, s in sets.items():
            if key[0] != VIEW_SA:
                continue
            _, th, _ = study.motion.frame.to_local(refs[key][s.track_id])
            th = np.mod(np.degrees(th), 360.0)
            subset(s, (th < lo_deg) | (th >= hi_deg))
        return sets

    return edit


def test_a_sector_whose_sa_tracks_are_lost_is_degraded_and_named(study):
    # A 100° sector loses its SA tracks on every slice (as an akinetic region's do): the solver
    # fills it with its neighbours' motion, and the phase must say so, naming where.
    m = study.motion
    es = int(round(m.es_phase))
    _, tr, refs = referenced_tracker(study, n=1000)
    sets = drop_sector(study, refs, 40.0, 140.0)(observed(study, refs, es))
    state = tr.solve(es, sets, m.num_phases).state
    assert state.verdict == DEGRADED and 'ED tag points lost' in state.verdict_reasons, (
        state.verdict_reasons
    )
    assert 'SA slices' in state.verdict_reasons
    assert any(name in state.verdict_reasons for name in AHA_SEGMENT_NAMES)
    # Degraded for the sector alone: the state names the segments its reason names, no other.
    named = {k + 1 for k, n in enumerate(AHA_SEGMENT_NAMES) if n in state.verdict_reasons}
    assert state.degraded_segments and set(state.degraded_segments) == named, (
        state.degraded_segments,
        state.verdict_reasons,
    )
    assert list(state.degraded_segments) == sorted(state.degraded_segments)
    # The same share of tracks lost evenly over the heart is no regional gap.
    even = solve(study, es, lambda s: keep(s, 0.7, seed=3))
    assert 'ED tag points lost' not in even.verdict_reasons, even.verdict_reasons
    assert even.degraded_segments == ()


def test_weakest_sector_finds_one_lost_sector_and_not_uniform_loss():
    theta = {k: np.arange(0.0, 360.0, 10.0) for k in range(8)}  # 8 SA rings, a point every 10°
    slices = {k: 18 for k in theta}
    # Slices 3–5 lose every point from 60° to 140°; everywhere one point in three is lost.
    lost = {
        k: (k in (3, 4, 5)) & (th >= 60.0) & (th < 150.0) | (np.arange(th.size) % 3 == 0)
        for k, th in theta.items()
    }
    tracks = {k: (th, ~lost[k], np.where(th < 180.0, 'a', 'b')) for k, th in theta.items()}
    sector = weakest_sector(tracks)
    assert sector.slices == (3, 4, 5) and sector.used == 0 and sector.share == 0.0
    assert sector.start_deg == 60.0 and sector.end_deg == 140.0 and sector.labels == ('a',)
    v = phase_verdict(100, 200, slices, 0.1, 1.0, sa_tracks=tracks)
    assert v.level == DEGRADED, v.text
    assert v.text.startswith('SA slices 3–5, θ 60–140° (a): 27 of 27 ED tag points lost'), v.text
    # Near ED (a small share of the largest displacement) a gap moves nothing: not judged.
    late = phase_verdict(100, 200, slices, 0.1, 1.0, sa_tracks=tracks, motion_share=0.2)
    assert late.level == OK, late.text
    # Half the points lost evenly (alternately, or at random): as well supported everywhere.
    alternate = {k: (th, np.arange(th.size) % 2 == k % 2) for k, th in theta.items()}
    rng = np.random.default_rng(0)
    scattered = {k: (th, rng.random(th.size) < 0.5) for k, th in theta.items()}
    for tracks in (alternate, scattered):
        assert weakest_sector(tracks).share > SECTOR_SHARE_DEGRADED
        assert phase_verdict(100, 200, slices, 0.1, 1.0, sa_tracks=tracks).level == OK
    # A sector wraps through 0°; one too sparse to judge is not judged.
    wrap = {k: (th, (th >= 40.0) & (th < 320.0)) for k, th in theta.items()}
    sector = weakest_sector(wrap, slices=2)
    assert sector.used == 2 and sector.start_deg == 320.0 and sector.end_deg == 390.0
    assert weakest_sector(wrap, min_points=40) is None
    assert weakest_sector({0: (theta[0], np.zeros(36, bool))}) is None  # nothing used at all
    with pytest.raises(ValueError, match='SA slice 0: 36 angles, 35 used flags'):
        weakest_sector({0: (theta[0], np.ones(35, bool))})
    with pytest.raises(ValueError, match='width_deg'):
        weakest_sector(wrap, width_deg=0.0)


def test_worst_fit_sector_finds_a_sector_whose_tracks_left_disagree_with_the_model():
    theta = {k: np.arange(0.0, 360.0, 10.0) for k in range(8)}  # 8 SA rings, a point every 10°
    slices = {k: 36 for k in theta}
    rng = np.random.default_rng(1)
    # One point in five lost everywhere, and the model leaves the rest ~0.1 mm off (localisation
    # noise, Rayleigh). On slices 3–4 from 60° to 110° the wall moves unlike its neighbours:
    # 8 of its 12 tracks lost, and the model, carrying it with them, leaves the 4 left 0.6 mm off.
    residual = {k: 0.1 * np.hypot(*rng.normal(size=(2, 36))) for k in theta}
    used = {k: np.arange(36) % 5 != 2 for k in theta}
    for k in (3, 4):
        sector = (theta[k] >= 60.0) & (theta[k] < 120.0)
        used[k][sector] = np.arange(36)[sector] % 3 == 0
        residual[k][sector] = 0.6
    names = {k: np.where(th < 180.0, 'a', 'b') for k, th in theta.items()}

    def tracks(residual, used=used):
        return {
            k: (theta[k], used[k], names[k], np.where(used[k], residual[k], np.nan))
            for k in theta
        }

    sector = worst_fit_sector(tracks(residual))
    assert sector.slices == (3, 4) and (sector.used, sector.points) == (4, 12), sector
    assert sector.start_deg == 60.0 and sector.end_deg == 110.0 and sector.labels == ('a',)
    assert sector.residual_mm == 0.6 and sector.ratio > FIT_SECTOR_RATIO
    v = phase_verdict(200, 288, slices, 0.1, 1.0, sa_tracks=tracks(residual))
    assert v.level == DEGRADED and len(v.reasons) == 1, v.text
    assert v.text.startswith(
        'SA slices 3–4, θ 60–110° (a): 8 of 12 ED tag points lost, the 4 left 0.60 mm'
    ), v.text
    # The lost-points check alone does not see it (a third of the sector's tracks are left).
    assert weakest_sector(tracks(residual)).share > SECTOR_SHARE_DEGRADED
    # Near ED a misfit moves nothing far: not judged; no residuals given: not judged.
    late = phase_verdict(200, 288, slices, 0.1, 1.0, sa_tracks=tracks(residual), motion_share=0.2)
    assert late.level == OK, late.text
    plain = {k: t[:3] for k, t in tracks(residual).items()}
    assert worst_fit_sector(plain) is None
    assert phase_verdict(200, 288, slices, 0.1, 1.0, sa_tracks=plain).level == OK
    # The tracks left followed as well as elsewhere (consistent with the solved motion): ok,
    # whatever the scale of the residuals (the rule is relative to the phase's own).
    for scale in (0.1, 1.0):
        even = {k: scale * np.hypot(*rng.normal(size=(2, 36))) for k in theta}
        assert worst_fit_sector(tracks(even)).ratio < FIT_SECTOR_RATIO
        assert phase_verdict(200, 288, slices, 0.1, 1.0, sa_tracks=tracks(even)).level == OK
    # The same misfit where no track was lost (a sector the model merely fits worse): not judged.
    kept = {k: np.arange(36) % 5 != 2 for k in theta}
    assert phase_verdict(200, 288, slices, 0.1, 1.0, sa_tracks=tracks(residual, kept)).level == OK
    assert worst_fit_sector(tracks(residual), min_used=5).ratio < FIT_SECTOR_RATIO
    with pytest.raises(ValueError, match='36 labels and 35 residuals'):
        worst_fit_sector({0: (theta[0], used[0], names[0], residual[0][:35])})
    with pytest.raises(ValueError, match='min_points'):
        worst_fit_sector(tracks(residual), min_used=0)


FR = oblique_frame()
X, ENDO = cylinder_shell(FR, r_in=20, r_out=30, n_r=4, n_theta=36, n_z=12)


@pytest.mark.parametrize(
    'motion, level, reason',
    [
        ({'s_r': 0.85, 's_l': 0.9, 'twist_apex_deg': 10, 'twist_base_deg': -3}, OK, ''),
        (
            {'s_r': 1.4, 's_l': 1.0, 'twist_apex_deg': 0, 'twist_base_deg': 0},
            FAILED,
            'ejection fraction',
        ),  # cavity ×2
        (
            {'s_r': 1.06, 's_l': 1.0, 'twist_apex_deg': 0, 'twist_base_deg': 0},
            DEGRADED,
            'ejection fraction',
        ),  # +12 %
    ],
)
def test_the_analyzer_marks_a_cavity_no_ventricle_has(motion, level, reason):
    x, F = cylindrical_motion(FR, X, **motion)
    m = LVAnalyzer(X, FR, endo_mask=ENDO).phase(x, F, phase_index=3, num_phases=10)
    assert m.verdict == level and reason in m.verdict_reasons, (
        m.ejection_fraction,
        m.verdict_reasons,
    )


def test_the_analyzer_marks_a_wall_point_that_travels_half_the_ventricle():
    x = X.copy()
    x[0] += 0.6 * FR.length * FR.axis  # one particle flung away
    m = LVAnalyzer(X, FR, endo_mask=ENDO).phase(x, phase_index=1, num_phases=10)
    assert m.verdict == FAILED and 'wall point moved' in m.verdict_reasons


def test_verdict_arithmetic_and_bad_levels():
    v = phase_verdict(50, 100, {0: 5, 1: 5}, 0.1, 1.0)
    assert v.level == OK and v.text == ''
    w = Verdict.from_parts(DEGRADED, 'a; b').merge(metrics_verdict(2.0, 1.0, 80.0))
    assert w.level == FAILED and w.reasons[:2] == ['a', 'b'] and 'ejection fraction' in w.text
    with pytest.raises(ValueError, match='verdict must be'):
        Verdict.from_parts(3, '')


def test_a_verdict_is_confined_to_a_region_only_while_every_reason_is_regional():
    v = Verdict()
    v.flag(DEGRADED, 'sector', region=('mid anterior', 'basal anterior'))
    assert v.level == DEGRADED and v.confined_to == ('mid anterior', 'basal anterior')
    v.flag(DEGRADED, 'fit residual')  # a whole-heart reason beside it: the whole phase
    assert v.confined_to == ()
    # Through a message: the solver's segments, then the analyzer's own verdict merged in.
    sent = Verdict.from_parts(DEGRADED, 'sector; another sector', (13, 7))
    assert sent.merge(Verdict()).confined_to == (13, 7)
    assert sent.merge(metrics_verdict(0.9, 1.0, 80.0)).confined_to == ()  # EF 90 %: degraded
    assert Verdict.from_parts(DEGRADED, 'x').confined_to == ()
    for level in (OK, FAILED):
        assert Verdict.from_parts(level, 'x' if level else '', (7,)).confined_to == ()
    failed = Verdict()
    failed.flag(FAILED, 'sector', region=(7,))
    assert failed.confined_to == ()


def _old_cdr(cls, cut: str, values: dict) -> bytes:
    """
    Serialise a ``cls`` message with rosbags under a definition cut before ``cut``.

    A ``cls`` message serialised by an independent writer (rosbags) under the definition that
    ends before the line starting ``cut`` (the fields appended since left out).
    """
    from pathlib import Path

    from rosbags.typesys import get_types_from_msg, get_typestore, Stores

    msgs = Path(__file__).resolve().parents[1] / 'msg_schemas' / 'msg'
    text = (msgs / f'{cls.__name__}.msg').read_text()
    store = get_typestore(Stores.ROS2_JAZZY)
    name = f'mlv_msgs/msg/{cls.__name__}'
    store.register(
        get_types_from_msg((msgs / 'SliceGeometry.msg').read_text(), 'mlv_msgs/msg/SliceGeometry')
    )
    store.register(get_types_from_msg(text[:text.index(cut)], name))
    Old, T = store.types[name], store.types
    header = T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=1, nanosec=2), frame_id='patient'
    )
    special = {
        'header': header,
        'translation': np.zeros(3),
        'rotation': np.array([1.0, 0, 0, 0]),
        'image': T['sensor_msgs/msg/Image'](
            header=header,
            height=2,
            width=3,
            encoding='mono8',
            is_bigendian=0,
            step=3,
            data=np.arange(6, dtype=np.uint8),
        ),
        'geometry': T['mlv_msgs/msg/SliceGeometry'](
            image_position=np.zeros(3),
            row_direction=np.array([1.0, 0, 0]),
            column_direction=np.array([0, 1.0, 0]),
            row_spacing=1.0,
            column_spacing=1.0,
            slice_thickness=6.0,
        ),
        'pixel_rc': np.zeros(0),
        'position': np.zeros(0),
        'track_id': np.zeros(0, np.int32),
        'confidence': np.zeros(0, np.float32),
    }
    kwargs = {}
    for f in Old.__dataclass_fields__:
        if f.startswith('__'):
            continue
        default = getattr(cls(), f)
        kwargs[f] = values.get(
            f,
            special.get(
                f, default if isinstance(default, (int, float, bool, str)) else np.asarray(default)
            ),
        )
    return bytes(store.serialize_cdr(Old(**kwargs), name))


def test_recordings_made_before_the_verdict_still_read():
    """
    Read recordings made before the verdict and study fields were appended.

    ModelState / MotionMetrics recorded before the verdict and the study fields, and before the
    study field alone, TaggedFrame / TagPoints before the study field (serialised by an
    independent writer, rosbags), read with the verdict ok, no study and every other field intact:
    the order the fields were appended in decides how (mlv_ros.bagio._APPENDED_FIELDS).
    """
    from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
    from mlv_ros import bagio

    cases = [
        (
            ModelState,
            '# Quality verdict',
            {'phase_index': 3, 'num_phases': 9, 'a0': 41.5, 'num_control_points': 77},
        ),
        (
            MotionMetrics,
            '# Quality verdict',
            {'phase_index': 2, 'num_phases': 9, 'cavity_volume_ml': 101.25},
        ),
        (
            TaggedFrame,
            '# Run isolation',
            {'phase_index': 2, 'num_phases': 9, 'series_uid': '1.2.3'},
        ),
        (TagPoints, '# Run isolation', {'phase_index': 2, 'num_phases': 9, 'status': 'abc'}),
    ]
    for reasons in ('', 'abc', 'abcd'):  # every alignment of the end of the older message
        cases += [
            (
                ModelState,
                '# Run isolation',
                {'phase_index': 3, 'num_phases': 9, 'verdict': 2, 'verdict_reasons': reasons},
            ),
            (
                MotionMetrics,
                '# Run isolation',
                {'phase_index': 2, 'verdict': 1, 'verdict_reasons': reasons},
            ),
        ]
    for sid in ('s', 'abcd'):  # recorded before run_id alone
        cases += [
            (
                cls,
                '# The run the message belongs to',
                {'phase_index': 1, 'num_phases': 9, 'study_id': sid},
            )
            for cls in (ModelState, MotionMetrics, TaggedFrame, TagPoints)
        ]
    for sid in (
        's',
        'abcd',
        'abcdefg',
    ):  # recorded before messages carried the segment origin and findings
        cases += [
            (
                ModelState,
                '# Where the circumferential reference',
                {'phase_index': 1, 'num_phases': 9, 'study_id': sid},
            ),
            (
                MotionMetrics,
                "# Where the AHA segments'",
                {'phase_index': 1, 'num_phases': 9, 'study_id': sid, 'cavity_volume_ml': 90.5},
            ),
        ]
    for sid in ('s', 'abcd', 'abcdefg'):  # recorded before TagPoints carried line normals
        cases.append(
            (TagPoints, '# Points on a single family', {'phase_index': 1, 'study_id': sid})
        )
    for sid in ('s', 'abcd', 'abcdefg'):  # recorded before TaggedFrame said single-line tags
        cases.append(
            (TaggedFrame, '# Single-line tags', {'phase_index': 1, 'study_id': sid})
        )
    for sid in ('s', 'abcd'):  # recorded before the degraded segments
        cases += [
            (
                cls,
                '# AHA segments (1-17, ascending)',
                {'phase_index': 1, 'num_phases': 9, 'study_id': sid, 'segment_origin': 2},
            )
            for cls in (ModelState, MotionMetrics)
        ]
    for cls, cut, values in cases:
        data = _old_cdr(cls, cut, values)
        name = f'mlv_msgs/msg/{cls.__name__}'
        text = bagio._msg_file('mlv_msgs', cls.__name__).read_text()
        missing = bagio.fields_missing_from(name, text[:text.index(cut)])
        for got in (
            bagio.deserialize(data, cls),
            bagio.deserialize(data, cls, missing),
        ):  # by trying, by schema
            assert got.study_id == values.get('study_id', '') and got.run_id == ''
            if 'verdict' not in values and hasattr(got, 'verdict'):
                assert got.verdict == 0 and got.verdict_reasons == ''
            for k, v in values.items():
                assert getattr(got, k) == v, (cls.__name__, cut, k)
            if hasattr(got, 'line_normal'):  # tag-grid intersections
                assert len(got.line_normal) == 0
            assert getattr(got, 'tag_lines', 0) == 0  # a tag grid
            assert len(getattr(got, 'degraded_segments', ())) == 0  # none named: the whole phase
            if 'segment_origin' in values:
                continue
            if hasattr(got, 'segment_origin'):  # unknown origin, no findings (ES phase −1)
                assert got.segment_origin == 0 and got.segment_origin_confidence == 0.0
                assert (
                    getattr(got, 'findings_es_phase', -1) == -1
                    and len(getattr(got, 'segment_class', b'')) == 0
                )
        assert (
            bagio.deserialize(bagio.current_cdr(data, cls), cls, ()).run_id == ''
        )  # what replay publishes
    assert (
        bagio.fields_missing_from(
            'mlv_msgs/msg/ModelState', bagio.message_definition('mlv_msgs/msg/ModelState')
        )
        == ()
    )
    with pytest.raises(ValueError, match='cannot deserialise'):
        bagio.deserialize(b'\x00\x01\x00\x00garbage', ModelState)


def test_run_summary_names_flagged_phases_and_an_untracked_study():
    from mlv_ros.runner import untracked, verdict_line, verdict_summary

    s = {
        'num_phases': 5,
        **verdict_summary(
            {0: (0, ''), 1: (0, ''), 2: (1, 'few points'), 3: (2, 'no SA slice'), 4: (0, '')}
        ),
    }
    assert s['phases_ok'] == [0, 1, 4] and s['phases_degraded'] == {'2': 'few points'}
    assert s['phases_failed'] == {'3': 'no SA slice'}
    line = verdict_line(s)
    assert '1 degraded (2)' in line and '1 failed (3)' in line and '\n' not in line
    assert not untracked(s)
    lost = {'num_phases': 3, **verdict_summary({0: (0, ''), 1: (2, 'x'), 2: (2, 'y')})}
    assert (
        untracked(lost)
        and verdict_line({'num_phases': 2, **verdict_summary({0: (0, ''), 1: (0, '')})}) is None
    )


def test_registration_and_ed_volume_verdicts():
    from types import SimpleNamespace as R

    from mlv_ros.core.verdict import registration_verdict

    ok = [R(view=0, slice_index=i, ok=True, reason='') for i in range(6)] + [
        R(view=1, slice_index=0, ok=True, reason='')
    ]
    assert registration_verdict(ok).level == OK
    few = [R(view=0, slice_index=i, ok=i < 2, reason='') for i in range(6)] + [
        R(view=1, slice_index=0, ok=False, reason='')
    ]
    v = registration_verdict(few)
    assert (
        v.level == DEGRADED and '2 of 6 SA slices' in v.text and 'none of the 1 LA views' in v.text
    )
    # LA views segmented but every horseshoe closed over the atrium: the base is not seen.
    sa = ok[:6]
    closed = [R(view=1, slice_index=i, ok=True, reason='', base_shown=False) for i in range(3)]
    v = registration_verdict(sa + closed)
    assert v.level == DEGRADED and 'no LA view shows the base' in v.text
    one_shows = closed[:2] + [R(view=1, slice_index=2, ok=True, reason='', base_shown=True)]
    assert registration_verdict(sa + one_shows).level == OK
    # Wall thickness: any adult heart passes, hypertrophic (20 mm, a 30 mm septum) and thinned
    # by a scar (3 mm over a tenth of the wall) included; a wall no heart has does not.
    rng = np.random.default_rng(0)
    for wall in (
        rng.normal(8.0, 1.0, 2000),
        rng.normal(20.0, 2.0, 2000),
        np.r_[rng.normal(8.0, 1.0, 1800), [3.0] * 200],
        np.r_[rng.normal(18.0, 2.0, 1800), [30.0] * 200],
        rng.normal(5.0, 0.5, 2000),
    ):
        assert registration_verdict(ok, wall).level == OK, registration_verdict(ok, wall).text
    thick = registration_verdict(ok, rng.normal(35.0, 2.0, 2000))
    assert thick.level == DEGRADED and 'ED wall thickness 35' in thick.text
    assert registration_verdict(ok, np.full(100, 0.8)).level == FAILED
    assert registration_verdict(ok, np.full(100, 80.0)).level == FAILED
    holed = registration_verdict(ok, np.r_[rng.normal(8.0, 1.0, 1800), [0.5] * 200])
    assert holed.level == DEGRADED and 'thin over 5 %' in holed.text
    assert registration_verdict(ok, []).level == OK  # no surfaces: not checked
    # A 40 605 ml EDV is not a heart; 1.2 l is a heart no adult has.
    assert metrics_verdict(0.3, 5.0, 80.0, edv_ml=40605.0).level == FAILED
    huge = metrics_verdict(0.3, 5.0, 80.0, edv_ml=1200.0)
    assert huge.level == DEGRADED and 'ED cavity volume' in huge.text
    assert metrics_verdict(0.3, 5.0, 80.0, edv_ml=140.0).level == OK


def test_registration_of_a_wall_no_adult_has_is_degraded():
    """
    Check the verdict on a phantom whose wall is 33 mm thick everywhere.

    A phantom whose wall is 33 mm thick everywhere (the segmentation takes it, each slice
    under its 35 mm bound): the registered model's mean wall is beyond the adult range, and the
    verdict says so with the thickness.
    """
    from mlv_ros.core.registration import register_ed
    from mlv_ros.core.sim import load_preset
    from mlv_ros.core.verdict import registration_verdict

    preset = load_preset('normal')
    preset['geometry'].update(
        endo_radius_mm=22.0, epi_radius_mm=55.0, endo_depth_mm=52.0
    )  # 33 mm walls
    thick = simulate_study(preset, snr=20, quick=True, num_phases=2)
    res = register_ed([f for f in thick.frames if f.phase_index == 0], num_particles=500, seed=0)
    wall = res.wall_thickness_mm()
    assert 28.0 < wall.mean() < 38.0
    v = registration_verdict(res.slice_reports, wall)
    assert (
        v.level == DEGRADED
        and 'ED wall thickness' in v.text
        and 'outside the adult range' in v.text
    )

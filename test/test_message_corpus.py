"""The message bad-input corpus (``corpus/message_cases.py``) through the live graph.

One in-process graph (tag detector, registration, solver, analyzer over real Fast DDS) gets a
valid 4-phase study with every corpus case interleaved: corrupt frames right after the frame
they were copied from, stand-in frames in place of the frame whose slot they take, corrupt tag
points among the frames, and — once the model is registered — corrupt motion clouds, model
states and registered-model messages. Every case must be reported by the node that consumes
it, naming it by its stamp, with the expected reason; legal stand-ins must come out as tag
points with nothing reported against them; no valid frame may be reported; every node must
still answer afterwards, and every phase must be solved and analysed.
"""

from collections import Counter

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from conftest import spin_until
from corpus.message_cases import message_cases
from graphkit import Probe, graph_nodes, wait_matched
from mlv_ros import conversions, qos
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.frame_source import count_slices, order_frames

PHASES = 4
MAX_PIXELS = 256 * 256
STAMP0 = 1000.0  # corpus stamps start here; valid frames are stamped 1, 2, ...
WARN, ERROR = DiagnosticStatus.WARN, DiagnosticStatus.ERROR


@pytest.fixture(scope="module")
def study():
    frames = order_frames(count_slices(list(simulate_study("normal", snr=20, quick=True, num_phases=PHASES).frames)),
                          "slice_major")
    valid = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(frames)]
    return valid, message_cases(valid, stamp0=STAMP0, max_pixels=MAX_PIXELS)


def test_corpus_has_every_kind():
    def study_msgs(num_phases):
        return [conversions.frame_to_msg(f) for f in count_slices(list(
            simulate_study("normal", quick=True, num_phases=num_phases).frames))]

    valid = study_msgs(3)
    cases = message_cases(valid)
    assert len(cases) >= 110 and len({c.name for c in cases}) == len(cases)
    assert len({conversions.stamp_text(c.msg.header.stamp) for c in cases}) == len(cases)
    kinds = Counter(c.category.split("/")[0] for c in cases)
    assert set(kinds) == {"frame", "tag_points", "motion", "model_state", "registered_cloud", "registered_state"}
    with pytest.raises(ValueError, match="SA and LA"):
        message_cases([m for m in valid if m.view == 0])
    with pytest.raises(ValueError, match="non-ED slots"):
        message_cases(study_msgs(2))


def _slot(m):
    return (m.view, m.slice_index, m.phase_index)


def test_every_case_is_reported_and_the_run_completes(study, ros_context, executor):
    valid, cases = study
    frames_cases = [c for c in cases if c.topic == qos.FRAMES]
    points_cases = [c for c in cases if c.topic == qos.TAG_POINTS]
    output_cases = [c for c in cases if c.topic in (qos.MOTION, qos.MODEL_STATE)]
    latched_cases = [c for c in cases if c.topic in qos.LATCHED_TOPICS]
    assert len(frames_cases) + len(points_cases) + len(output_cases) + len(latched_cases) == len(cases)
    stand_ins = {c.replaces: c for c in frames_cases if c.replaces}
    after = {}
    for c in frames_cases:
        if c.after:
            after.setdefault(c.after, []).append(c)

    nodes = graph_nodes(ros_context, max_pixels=MAX_PIXELS)
    probe = Probe(ros_context)
    for n in (*nodes.values(), probe):
        executor.add_node(n)
    wait_matched(executor, probe, {qos.FRAMES: 2, qos.TAG_POINTS: 1, qos.MOTION: 1, qos.MODEL_STATE: 1,
                                   qos.REGISTERED_CLOUD: 2, qos.REGISTERED_STATE: 2})
    solver, analyzer = nodes["meshless_solver"], nodes["motion_analyzer"]

    # 1. Frames, each followed by the corrupt copies made from it; the solver takes the study's
    # dimensions from the first genuine tag points, then corrupt tag points go in among the frames.
    for i, m in enumerate(valid):
        probe.publish(qos.FRAMES, stand_ins[_slot(m)].msg if _slot(m) in stand_ins else m)
        for c in after.get(_slot(m), []):
            probe.publish(qos.FRAMES, c.msg)
        if i == 0:
            assert spin_until(executor, lambda: solver.messages_handled >= 1, 30), "no tag points reached the solver"
        elif points_cases:
            probe.publish(qos.TAG_POINTS, points_cases.pop().msg)
    for c in points_cases:
        probe.publish(qos.TAG_POINTS, c.msg)

    # 2. Once solver and analyzer hold the model (so a wrong point count is detectable), corrupt
    # outputs go in while phases are still being solved. Latched topics keep one message per
    # reader (KEEP_LAST(1)): a case sent before the genuine model was taken would displace it, so
    # those cases go after it, one at a time.
    assert spin_until(executor, lambda: solver.tracker is not None and analyzer.analyzer is not None, 60), \
        probe.statuses()[-10:]
    for c in output_cases:
        probe.publish(c.topic, c.msg)

    def reports(case):
        return [(lvl, f"{msg} {vals}".lower()) for node, lvl, msg, vals in probe.statuses()
                if node == case.node and vals.get("stamp") == case.stamp]

    for c in latched_cases:
        probe.publish(c.topic, c.msg)
        assert spin_until(executor, lambda c=c: reports(c), 60), f"{c.name}: not reported"

    # 3. The run completes, and every case has been reported (or, if legal, processed).
    stamps_out = lambda: {conversions.stamp_text(p.header.stamp) for p in probe.received("points")}  # noqa: E731
    legal = [c for c in cases if not c.expect]
    assert spin_until(executor, lambda: len(probe.received("metrics")) >= PHASES
                      and all(reports(c) for c in cases if c.expect)
                      and {c.stamp for c in legal} <= stamps_out(), 120), \
        f"{len(probe.out['metrics'])} phases analysed; unreported: {[c.name for c in cases if c.expect and not reports(c)]}"

    failures = []
    for c in cases:
        got = reports(c)
        if c.expect:
            want = WARN if c.category == "frame/content" else ERROR
            if not any(lvl == want and c.expect in text for lvl, text in got):
                failures.append(f"{c.name}: want level {want} with {c.expect!r}, got {got}")
        else:
            points = [p for p in probe.received("points") if conversions.stamp_text(p.header.stamp) == c.stamp]
            if any(lvl == ERROR for lvl, _ in got) or not (len(points) == 1 and len(points[0].track_id) > 0):
                failures.append(f"{c.name}: legal frame not processed: {got}, {[p.status for p in points]}")
    assert not failures, "\n".join(failures)

    # No false alarms: nothing is reported as bad about a valid frame.
    valid_stamps = {conversions.stamp_text(m.header.stamp) for m in valid}
    wrong = [s for s in probe.statuses() if s[1] == ERROR and s[3].get("stamp") in valid_stamps]
    assert not wrong, wrong

    # Corrupt copies never displaced a genuine tag set: one set per slot, no duplicates downstream.
    assert nodes["tag_detector"].frames_out == len(valid)
    assert not [s for s in probe.statuses() if s[0] == "meshless_solver" and "duplicate" in s[2]]

    # Every phase solved and analysed exactly once.
    assert sorted(s.phase_index for s in probe.received("state")) == list(range(PHASES))
    assert sorted(m.phase_index for m in probe.received("metrics")) == list(range(PHASES))

    # Every node still up and answering: a heartbeat from each after the corpus.
    seen = len(probe.out["diag"])
    assert spin_until(executor, lambda: {s.hardware_id for d in probe.out["diag"][seen:] for s in d.status}
                      >= set(nodes), 5), "a node stopped publishing its status"
    counts = Counter(c.category for c in cases)
    print(f"\n{len(cases)} cases, all reported by the consuming node: {dict(sorted(counts.items()))}")

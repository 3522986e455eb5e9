"""Offline re-track and re-solve of a recorded run, with the code the nodes use.

Reads a run's recorded frames and registration (``run.mcap`` of ``mlv-ros run --dicom``),
tracks every slice again as the tag detector does (:class:`StreamingMasker` ED masks +
:class:`SliceTracker`), solves every phase as the solver node does (:class:`MotionTracker` with
the node's default parameters) and scores the result against the study's ``groundtruth.json``
as ``bench/robustness.py`` does. A tracking or solving change can then be compared on the same
studies without the graph (seconds to a minute per study instead of minutes).

    python bench/retrack.py CASE_DIR [CASE_DIR ...]     # CASE_DIR holds run/run.mcap and study/

Prints one JSON line per case: ES median / p95 (mm), twist error (all levels and where SA slices
are), phases solved / degraded / failed, worst phase median, seconds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import yaml
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

from mlv_msgs.msg import ModelState, TaggedFrame
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.io.groundtruth import motion_from_groundtruth
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.tags import SliceTracker
from mlv_ros.core.tracking import MotionTracker
from mlv_ros.core.verdict import FAILED, OK
from mlv_ros.tools.run import _accuracy


def recorded(mcap: Path):
    """Frames in recorded order, the registered cloud and state."""
    frames, cloud, state = [], None, None
    for m in bagio.read_bag(mcap, topics=[qos.FRAMES, qos.REGISTERED_CLOUD, qos.REGISTERED_STATE],
                            any_namespace=True):
        if m.topic == qos.FRAMES:
            frames.append(conversions.msg_to_frame(deserialize_message(m.data, TaggedFrame), allow_nonfinite=True))
        elif m.topic == qos.REGISTERED_CLOUD:
            cloud = conversions.msg_to_cloud(deserialize_message(m.data, PointCloud2))
        else:
            state = conversions.msg_to_model_state(bagio.deserialize(m.data, ModelState, m.missing))
    return frames, cloud, state


def track(frames, **tracker_kwargs) -> dict:
    """``{phase: {(view, slice): TagPointSet}}`` as the tag detector node makes them."""
    masker, trackers, sets = StreamingMasker(), {}, {}
    pending: dict = {}
    for f in frames:
        masker.observe_geometry(f)
        key = (f.view, f.slice_index)
        pending.setdefault(key, []).append(f)
    # The node processes each slice's frames in phase order as they come; the masker has seen
    # every geometry by then only if the frames came slice-major, so observe them in order.
    for f in frames:
        key = (f.view, f.slice_index)
        mask = None
        if f.phase_index == 0 or key not in trackers:
            trackers[key] = SliceTracker(f.geometry, **tracker_kwargs)
            mask, _ = masker.ed_mask(f)
        pts = trackers[key].update(f, mask=mask)
        sets.setdefault(int(f.phase_index), {})[key] = pts
    return sets


def solve(sets: dict, cloud, state, **solver_kwargs):
    """Every phase solved as the solver node does; keywords MotionTracker does not take are set as
    its attributes (``outlier_mm``, ``prescreen``, ...)."""
    import inspect

    known = inspect.signature(MotionTracker).parameters
    attrs = {k: solver_kwargs.pop(k) for k in list(solver_kwargs) if k not in known}
    tr = MotionTracker(conversions.xyz(cloud), state.translation, state.rotation,
                       polar=(cloud["alpha"], cloud["beta"], cloud["w"]),
                       shape=(state.a0, state.a1, state.a2, state.a3, state.tau), **solver_kwargs)
    for k, v in attrs.items():
        if not hasattr(tr, k):
            raise ValueError(f"MotionTracker has no parameter or attribute {k!r}")
        setattr(tr, k, v)
    for pts in sets.get(0, {}).values():
        tr.set_reference(pts)
    n = max(sets) + 1
    positions, verdicts = {0: tr.rest}, {}
    for p in range(1, n):
        try:
            sol = tr.solve(p, sets.get(p, {}), n)
        except ValueError as exc:
            verdicts[p] = (FAILED, f"not solved: {exc}")
            continue
        positions[p] = sol.positions
        verdicts[p] = (sol.state.verdict, sol.state.verdict_reasons)
    return tr, positions, verdicts


def replay_case(case: Path, tracker_kwargs=None, solver_kwargs=None) -> dict:
    t0 = time.monotonic()
    frames, cloud, state = recorded(case / "run" / "run.mcap")
    sets = track(frames, **(tracker_kwargs or {}))
    t1 = time.monotonic()
    tr, positions, verdicts = solve(sets, cloud, state, **(solver_kwargs or {}))
    sa_planes = [(p.geometry.image_position, p.geometry.normal) for (v, _), p in sets.get(0, {}).items()
                 if v == TaggedFrame.VIEW_SA and len(p.track_id)]
    run = {"ed": tr.rest, "rotation": state.rotation, "positions": positions, "sa_planes": sa_planes}
    acc = _accuracy(run, motion_from_groundtruth(case / "study"))
    es = acc["es"] or {}
    return {"case": case.name,
            **{k: round(es[k], 3) for k in ("median_mm", "p95_mm", "twist_error_deg", "twist_error_measured_deg")
               if k in es},
            "coverage": round(acc["coverage"], 3),
            "solved": f"{len(positions)}/{max(sets) + 1}",
            "degraded": sorted(p for p, (v, _) in verdicts.items() if OK < v < FAILED),
            "failed": sorted(p for p, (v, _) in verdicts.items() if v >= FAILED),
            "worst_phase_median_mm": round(max(r["median_mm"] for r in acc["per_phase"]), 3),
            "track_s": round(t1 - t0, 1), "solve_s": round(time.monotonic() - t1, 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", type=Path)
    ap.add_argument("--tracker", action="append", default=[], metavar="KEY=VALUE",
                    help="SliceTracker keyword (a number or true/false), repeatable")
    ap.add_argument("--solver", action="append", default=[], metavar="KEY=VALUE",
                    help="MotionTracker keyword (a number or true/false), repeatable")
    args = ap.parse_args()
    kw = [{k: yaml.safe_load(v) for k, v in (a.split("=", 1) for a in opts)} for opts in (args.tracker, args.solver)]
    for case in args.cases:
        print(json.dumps(replay_case(case, *kw) | ({"tracker": kw[0]} if kw[0] else {})
                         | ({"solver": kw[1]} if kw[1] else {})), flush=True)


if __name__ == "__main__":
    sys.exit(main())

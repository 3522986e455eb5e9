"""Benchmark: the whole graph on the default study (normal phantom, 8 SA + 3 LA, 256², 25 phases,
SNR 20) in one process. Prints one JSON document: total time, per-stage latency per phase
(from the recording's receive times), peak RSS, messages published vs recorded, accuracy.

    mlv-ros bench pipeline [-- --phases 25 --size 256 --out DIR]
"""

import argparse
import json
import resource
import statistics
import tempfile
import time
from pathlib import Path

from rclpy.serialization import deserialize_message

from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
from mlv_ros import bagio, qos
from mlv_ros.tools.run import phantom_accuracy, run_graph


def stage_latencies(mcap: Path) -> dict:
    """Per-phase latencies (ms) from receive times in the recording: frame → tag points (per
    frame), last tag points of a phase → its motion (solver), motion → metrics (analyzer)."""
    frame_t, tag_t, motion_t, metrics_t = {}, {}, {}, {}
    for m in bagio.read_bag(mcap, topics=[qos.FRAMES, qos.TAG_POINTS, qos.MODEL_STATE, qos.METRICS]):
        if m.topic == qos.FRAMES:
            f = deserialize_message(m.data, TaggedFrame)
            frame_t[(f.view, f.slice_index, f.phase_index)] = m.log_time_ns
        elif m.topic == qos.TAG_POINTS:
            p = deserialize_message(m.data, TagPoints)
            tag_t[(p.view, p.slice_index, p.phase_index)] = m.log_time_ns
        elif m.topic == qos.MODEL_STATE:
            motion_t[deserialize_message(m.data, ModelState).phase_index] = m.log_time_ns
        else:
            metrics_t[deserialize_message(m.data, MotionMetrics).phase_index] = m.log_time_ns
    tag_ms = [(tag_t[k] - frame_t[k]) / 1e6 for k in tag_t if k in frame_t]
    solve_ms = []
    for ph, t in motion_t.items():
        last_tag = max((v for k, v in tag_t.items() if k[2] == ph), default=None)
        if last_tag is not None and ph > 0:
            solve_ms.append((t - last_tag) / 1e6)
    analyse_ms = [(metrics_t[ph] - t) / 1e6 for ph, t in motion_t.items() if ph in metrics_t]

    def stats(v):
        return {"median": round(statistics.median(v), 1), "max": round(max(v), 1), "n": len(v)} if v else {}

    return {"tag_detector_per_frame_ms": stats(tag_ms), "solver_per_phase_ms": stats(solve_ms),
            "analyzer_per_phase_ms": stats(analyse_ms)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--phases", type=int, default=25)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--preset", default="normal")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="mlv-bench-pipeline-"))
    t0 = time.perf_counter()
    s = run_graph({"source": "phantom", "preset": args.preset, "size": args.size, "num_phases": args.phases},
                  out, progress=lambda *_: None)
    wall = time.perf_counter() - t0
    topics = bagio.bag_topics(out / "run.mcap")
    acc = phantom_accuracy(out / "run.mcap", args.preset, args.phases) if s["complete"] else {}
    published = {qos.FRAMES: s["frames_published"], qos.TAG_POINTS: s["tag_sets_published"],
                 qos.MOTION: s["phases_solved"], qos.MODEL_STATE: s["phases_solved"],
                 qos.METRICS: s["metrics_published"]}
    result = {
        "benchmark": "pipeline", "preset": args.preset, "size": args.size, "phases": args.phases,
        "slices": 11, "total_s": round(wall, 2), "graph_s": s["seconds"],
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "latency": stage_latencies(out / "run.mcap"),
        "published_vs_recorded": {t: [published[t], topics.get(t, {}).get("count", 0)] for t in published},
        "all_recorded": all(published[t] == topics.get(t, {}).get("count", 0) for t in published),
        "accuracy_es": acc.get("es"), "complete": s["complete"], "run_dir": str(out),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

"""``mlv-ros run``: the whole graph in one process (one executor), recorded to RUN_DIR/run.mcap.

    mlv-ros run (--phantom PRESET | --dicom DIR | --bag FILE) --out RUN_DIR

Shows progress per phase, prints a JSON summary (counts, timings, and accuracy against the
ground truth when the input is a phantom) and writes it to RUN_DIR/summary.json.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import yaml

GRAPH = ["recorder", "motion_analyzer", "meshless_solver", "registration", "tag_detector", "frame_source"]


def add_arguments(parser):
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--phantom", metavar="PRESET", help="simulate a preset (normal, hypertrophic, dilated, infarct, cylinder)")
    src.add_argument("--dicom", metavar="DIR", help="read a DICOM directory")
    src.add_argument("--bag", metavar="FILE", help="replay the frames of a recorded MCAP")
    parser.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (must not hold a run.mcap)")
    parser.add_argument("--params", default=None, help="graph parameters YAML (default config/graph.yaml)")
    parser.add_argument("--snr", type=float, default=None, help="phantom SNR (default from the params file)")
    parser.add_argument("--size", type=int, default=None, help="phantom image size, pixels")
    parser.add_argument("--phases", type=int, default=None, help="phantom phases per cycle")
    parser.add_argument("--order", choices=("slice_major", "phase_major"), default=None)
    parser.add_argument("--particles", type=int, default=None, help="model particles")
    parser.add_argument("--masks", default=None, help="NIfTI label image of the ED myocardium (label 2) instead of automatic segmentation")
    parser.add_argument("--timeout", type=float, default=600.0, help="give up after this many seconds")
    parser.add_argument("--quiet", action="store_true", help="no per-phase progress lines")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS domain to run on (default: $ROS_DOMAIN_ID if set, else a free private one)")


def node_parameters(params_file: Path, overrides: dict) -> dict:
    """{node: [rclpy Parameter]} from the graph YAML plus overrides {node: {name: value}}."""
    from rclpy.parameter import Parameter

    data = yaml.safe_load(params_file.read_text()) or {}
    out = {}
    for node in GRAPH:
        values = dict((data.get(node) or {}).get("ros__parameters") or {})
        values.update(overrides.get(node, {}))
        out[node] = [Parameter(k, value=v) for k, v in values.items()]
    return out


def run_graph(source: dict, out_dir: Path, params_file: Path | None = None, overrides: dict | None = None,
              timeout: float = 600.0, progress=print, domain_id: int | None = None) -> dict:
    """Run the graph on ``source`` ({"source": "phantom"|"dicom"|"bag"|"pattern", ...frame_source
    parameters}) and record to ``out_dir/run.mcap``. Returns the summary dict.

    ``domain_id``: the ROS domain the graph talks on; default ``ROS_DOMAIN_ID`` when the caller
    set it, else a private one claimed for this process (so parallel runs never mix)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from mlv_ros.nodes.frame_source import FrameSource
    from mlv_ros.nodes.meshless_solver import MeshlessSolver
    from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
    from mlv_ros.nodes.recorder import Recorder
    from mlv_ros.nodes.registration import Registration
    from mlv_ros.nodes.tag_detector import TagDetector
    from mlv_ros.domain import claim_domain_id
    from mlv_ros.resources import config_file

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    out_dir = Path(out_dir)
    mcap = out_dir / "run.mcap"
    if mcap.exists():
        raise FileExistsError(f"{mcap} exists: choose a new --out directory (runs are never overwritten)")
    overrides = {k: dict(v) for k, v in (overrides or {}).items()}
    overrides.setdefault("frame_source", {}).update(source)
    overrides.setdefault("recorder", {})["output"] = str(mcap)
    params = node_parameters(Path(params_file) if params_file else config_file("graph.yaml"), overrides)
    classes = {"recorder": Recorder, "motion_analyzer": MotionAnalyzer, "meshless_solver": MeshlessSolver,
               "registration": Registration, "tag_detector": TagDetector, "frame_source": FrameSource}
    if domain_id is None:
        domain_id = int(os.environ["ROS_DOMAIN_ID"]) if os.environ.get("ROS_DOMAIN_ID") else claim_domain_id()
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    t0 = time.monotonic()
    nodes = {}
    try:
        ex = SingleThreadedExecutor(context=ctx)
        for name in GRAPH:  # downstream first, so every subscriber exists before frames flow
            nodes[name] = classes[name](context=ctx, parameter_overrides=params[name])
            ex.add_node(nodes[name])
        src, solver, analyzer, rec = nodes["frame_source"], nodes["meshless_solver"], nodes["motion_analyzer"], nodes["recorder"]
        num_phases = max((f.num_phases for f in src.frames), default=0)
        progress(f"[mlv-ros] {len(src.frames)} frames, {num_phases} phases -> {mcap} (ROS_DOMAIN_ID={domain_id})")
        seen = 0
        while time.monotonic() - t0 < timeout:
            ex.spin_once(timeout_sec=0.05)
            if analyzer.published > seen:
                seen = analyzer.published
                progress(f"[mlv-ros] phase {seen}/{num_phases} analysed ({time.monotonic() - t0:.1f} s)")
            if src.done and num_phases and analyzer.published >= num_phases:
                break
            if src.done and num_phases and solver.next_phase >= num_phases and not analyzer.clouds:
                break  # every phase attempted (some may have failed; diagnostics say which)
            if nodes["registration"].registered and nodes["registration"].result is None and src.done:
                break  # registration failed: nothing downstream can happen
        # let the recorder take what is still queued
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            ex.spin_once(timeout_sec=0.05)
        rec.finish()
        elapsed = time.monotonic() - t0
        summary = {
            "source": source, "run_dir": str(out_dir), "mcap": str(mcap), "ros_domain_id": domain_id,
            "seconds": round(elapsed, 2),
            "frames_published": src.published, "tag_sets_published": nodes["tag_detector"].frames_out,
            "phases_solved": solver.phases_published, "metrics_published": analyzer.published,
            "num_phases": num_phases, "recorded_messages": rec.writer.message_count,
            "diagnostics_sent": sum(n.diagnostics_sent for n in nodes.values()),
            "complete": bool(num_phases) and analyzer.published >= num_phases,
        }
    finally:
        for node in nodes.values():
            node.destroy_node()
        ctx.try_shutdown()
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def read_run(mcap: Path) -> dict:
    """Registered cloud/state, motion positions and metrics per phase from a recording."""
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import PointCloud2

    from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
    from mlv_ros import bagio, conversions, qos

    run = {"positions": {}, "states": {}, "metrics": {}, "ed": None, "rotation": None, "frames": 0,
           "sa_planes": []}  # (point, normal) of every SA plane with ED tag points
    stamps = {}
    clouds = {}
    for m in bagio.read_bag(mcap):
        if m.topic == qos.REGISTERED_CLOUD:
            run["ed"] = conversions.xyz(conversions.msg_to_cloud(deserialize_message(m.data, PointCloud2)))
        elif m.topic == qos.REGISTERED_STATE:
            run["rotation"] = conversions.msg_to_model_state(deserialize_message(m.data, ModelState)).rotation
        elif m.topic == qos.MOTION:
            msg = deserialize_message(m.data, PointCloud2)
            clouds[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = conversions.xyz(conversions.msg_to_cloud(msg))
        elif m.topic == qos.MODEL_STATE:
            msg = deserialize_message(m.data, ModelState)
            stamps[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg.phase_index
            run["states"][msg.phase_index] = conversions.msg_to_model_state(msg)
        elif m.topic == qos.METRICS:
            d = conversions.msg_to_metrics(deserialize_message(m.data, MotionMetrics))
            run["metrics"][d["phase_index"]] = d
        elif m.topic == qos.FRAMES:
            run["frames"] += 1
        elif m.topic == qos.TAG_POINTS:
            msg = deserialize_message(m.data, TagPoints)
            if msg.view == TaggedFrame.VIEW_SA and msg.phase_index == 0 and len(msg.track_id):
                g = conversions.msg_to_geometry(msg.geometry)
                run["sa_planes"].append((g.image_position, g.normal))
    for key, x in clouds.items():
        if key in stamps:
            run["positions"][stamps[key]] = x
    return run


def phantom_accuracy(mcap: Path, preset: str, num_phases: int) -> dict:
    """Accuracy of a recorded phantom run against the preset's analytic motion."""
    from mlv_ros.core.sim import load_preset, make_motion

    run = read_run(mcap)
    if run["ed"] is None or not run["positions"]:
        return {"error": "the run has no registered model or no motion to evaluate"}
    return _accuracy(run, make_motion(load_preset(preset), num_phases=num_phases))


def _accuracy(run: dict, motion) -> dict:
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.evaluation import evaluate_run
    from mlv_ros.core.tracking import lv_frame_axes

    apex, base, ref = lv_frame_axes(run["ed"], run["rotation"])
    analyzer = LVAnalyzer(run["ed"], LVFrame(apex, base, ref))
    span = None
    if run.get("sa_planes"):
        axis = base - apex
        h = [float((p - apex) @ n / (axis @ n)) for p, n in run["sa_planes"] if abs(axis @ n) > 1e-6]
        span = (min(h), max(h)) if h else None
    return evaluate_run(run["ed"], run["positions"], motion, analyzer, sa_span=span)


def groundtruth_accuracy(mcap: Path, groundtruth: Path) -> dict:
    """Accuracy of a recorded run against a simulated study's ``groundtruth.json`` (its directory
    or the file), as :func:`phantom_accuracy` does for a preset."""
    from mlv_ros.core.io.groundtruth import motion_from_groundtruth

    run = read_run(mcap)
    if run["ed"] is None or not run["positions"]:
        return {"error": "the run has no registered model or no motion to evaluate"}
    return _accuracy(run, motion_from_groundtruth(groundtruth))


def find_groundtruth(dicom_dir: Path) -> Path | None:
    """``groundtruth.json`` of a simulated study: in the DICOM directory or its parent."""
    for d in (dicom_dir, dicom_dir.parent):
        if (d / "groundtruth.json").is_file():
            return d / "groundtruth.json"
    return None


def run(args) -> int:
    if args.phantom:
        source = {"source": "phantom", "preset": args.phantom}
        for key, val in (("snr", args.snr), ("size", args.size), ("num_phases", args.phases)):
            if val is not None:
                source[key] = float(val) if key == "snr" else int(val)
    elif args.dicom:
        source = {"source": "dicom", "path": str(Path(args.dicom).resolve())}
    else:
        source = {"source": "bag", "path": str(Path(args.bag).resolve())}
    if args.order:
        source["order"] = args.order
    overrides = {"registration": {}}
    if args.particles:
        overrides["registration"]["num_particles"] = args.particles
    if args.masks:
        overrides["registration"]["mask_path"] = str(Path(args.masks).resolve())
    try:
        summary = run_graph(source, Path(args.out), args.params, overrides, args.timeout,
                            progress=(lambda *_: None) if args.quiet else (lambda s: print(s, file=sys.stderr)),
                            domain_id=args.domain_id)
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        print(f"mlv-ros run: {exc}", file=sys.stderr)
        return 2
    truth = find_groundtruth(Path(args.dicom)) if args.dicom else None
    if (args.phantom or truth) and summary["complete"]:
        acc = (phantom_accuracy(Path(summary["mcap"]), args.phantom, summary["num_phases"]) if args.phantom
               else groundtruth_accuracy(Path(summary["mcap"]), truth))
        summary["accuracy"] = {"es_phase": acc.get("es_phase"), "es": acc.get("es"),
                               "inside_myocardium": acc.get("inside_myocardium"),
                               "coverage": acc.get("coverage"),
                               "per_phase": acc.get("per_phase")}
        Path(args.out, "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps({k: v for k, v in summary.items() if k != "accuracy"} | (
        {"accuracy_es": summary["accuracy"]["es"]} if "accuracy" in summary else {}), indent=2))
    return 0 if summary["complete"] else 1

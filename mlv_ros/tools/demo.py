"""``mlv-ros demo``: the README's main command. Runs what the pipeline has on the built-in
phantom (the simulator's ``normal`` preset when present, else the analytic test pattern) and
prints a summary."""

from __future__ import annotations

import json
import os
import time


def add_arguments(parser):
    parser.add_argument("--out", default="runs/demo", help="run directory (default: runs/demo)")


def run(args) -> int:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from mlv_msgs.msg import TaggedFrame
    from mlv_ros import qos
    from mlv_ros.nodes.frame_source import FrameSource

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    try:
        import mlv_ros.core.sim  # noqa: F401
        source = "phantom"
    except ImportError:
        source = "pattern"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        ex = SingleThreadedExecutor(context=ctx)
        sink = rclpy.create_node("demo_sink", context=ctx)
        got = []
        sink.create_subscription(TaggedFrame, qos.FRAMES, got.append, qos.stream_qos())
        t0 = time.monotonic()
        src = FrameSource(context=ctx, parameter_overrides=[Parameter("source", value=source)])
        ex.add_node(sink)
        ex.add_node(src)
        while not src.done and time.monotonic() - t0 < 120:
            ex.spin_once(timeout_sec=0.1)
        summary = {"source": source, "frames_published": src.published, "frames_received": len(got),
                   "seconds": round(time.monotonic() - t0, 2)}
    finally:
        ctx.try_shutdown()
    print(json.dumps(summary, indent=2))
    return 0 if summary["frames_received"] == summary["frames_published"] > 0 else 1

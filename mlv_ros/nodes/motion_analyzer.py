"""motion_analyzer: per-phase motion metrics from /lv/motion (→ /lv/metrics).

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class MotionAnalyzer(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("motion_analyzer", **node_kwargs)
        self.report(WARN, "motion_analyzer is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(MotionAnalyzer, args)


if __name__ == "__main__":
    raise SystemExit(main())

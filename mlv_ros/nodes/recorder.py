"""recorder: records every graph topic to MCAP (rosbag2 conventions).

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class Recorder(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("recorder", **node_kwargs)
        self.report(WARN, "recorder is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(Recorder, args)


if __name__ == "__main__":
    raise SystemExit(main())

"""replay: publishes a recorded MCAP's topics with original timing or as fast as possible.

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class Replay(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("replay", **node_kwargs)
        self.report(WARN, "replay is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(Replay, args)


if __name__ == "__main__":
    raise SystemExit(main())

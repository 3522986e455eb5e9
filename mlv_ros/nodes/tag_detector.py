"""tag_detector: detects and tracks tag intersections per frame (/mlv/frames → /mlv/tag_points).

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class TagDetector(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("tag_detector", **node_kwargs)
        self.report(WARN, "tag_detector is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(TagDetector, args)


if __name__ == "__main__":
    raise SystemExit(main())

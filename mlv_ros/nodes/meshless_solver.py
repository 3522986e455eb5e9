"""meshless_solver: solves each phase's dense motion from tag constraints (→ /lv/motion, /lv/model_state).

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class MeshlessSolver(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("meshless_solver", **node_kwargs)
        self.report(WARN, "meshless_solver is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(MeshlessSolver, args)


if __name__ == "__main__":
    raise SystemExit(main())

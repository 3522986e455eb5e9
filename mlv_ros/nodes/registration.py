"""registration: registers the meshless model to the ED images (→ /mlv/registered_cloud, /mlv/registered_state).

Not implemented yet: the node starts, declares its interface, reports on /diagnostics and spins.
"""

from __future__ import annotations

from mlv_ros.nodes.common import WARN, GraphNode, run_node


class Registration(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("registration", **node_kwargs)
        self.report(WARN, "registration is a placeholder in this version; it only spins")


def main(args=None):
    return run_node(Registration, args)


if __name__ == "__main__":
    raise SystemExit(main())

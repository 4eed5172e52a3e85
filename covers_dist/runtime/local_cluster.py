"""A loopback-only multi-node Ray cluster on this machine, for benchmarks and fault tests.

Built on ``ray.cluster_utils.Cluster``: a head node and worker nodes as separate Ray node
processes, every process bound to 127.0.0.1, all under one temp dir of the cluster's own. Nodes
can be added and removed while a run uses the cluster (``remove_node`` kills that node's raylet,
object store and worker processes, as a lost machine would). Stop it with :meth:`shutdown`, which
ends exactly the processes it started.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LocalCluster"]


class LocalCluster:
    """``LocalCluster(head_cpus)``; ``add_node(num_cpus)``; ``remove_node(node)``; ``shutdown()``."""

    def __init__(self, head_cpus: int, head_resources: dict[str, float] | None = None) -> None:
        from .ray_setup import loopback_only, ray_temp_dir

        loopback_only()  # every node binds and talks on 127.0.0.1
        import ray._common.utils as common_utils
        import ray._private.utils as private_utils
        from ray.cluster_utils import Cluster

        self.temp_dir = ray_temp_dir()
        # cluster_utils records (and at shutdown deletes) "the current cluster" in Ray's machine-wide
        # default temp dir, where any other ray.init() on the machine would find it: keep it in ours
        self._write, self._reset = private_utils.write_ray_address, common_utils.reset_ray_address
        private_utils.write_ray_address = lambda address, temp_dir=None: self._write(address, temp_dir or self.temp_dir)
        common_utils.reset_ray_address = lambda temp_dir=None: self._reset(temp_dir or self.temp_dir)
        self._modules = (private_utils, common_utils)
        try:
            self.cluster = Cluster(
                initialize_head=True,
                head_node_args={**self._node_args(head_cpus, head_resources), "include_dashboard": False},
            )
        except BaseException:
            self._restore()
            raise
        self.head = self.cluster.head_node

    def _node_args(self, num_cpus: int, resources: dict[str, float] | None) -> dict[str, Any]:
        return {"num_cpus": num_cpus, "node_ip_address": "127.0.0.1", "temp_dir": self.temp_dir, "resources": resources or {}}

    @property
    def address(self) -> str:
        return self.cluster.address

    def add_node(self, num_cpus: int, resources: dict[str, float] | None = None) -> Any:
        node = self.cluster.add_node(**self._node_args(num_cpus, resources))
        self.cluster.wait_for_nodes()
        return node

    def remove_node(self, node: Any) -> None:
        """Kill a (non-head) node's processes at once, as a machine that is lost."""
        self.cluster.remove_node(node, allow_graceful=False)

    def _restore(self) -> None:
        private_utils, common_utils = self._modules
        private_utils.write_ray_address, common_utils.reset_ray_address = self._write, self._reset

    def shutdown(self) -> None:
        """Disconnect this process (if connected) and stop every node this cluster started."""
        import ray

        try:
            if ray.is_initialized():
                ray.shutdown()
            self.cluster.shutdown()
        finally:
            self._restore()

    def __enter__(self) -> "LocalCluster":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.shutdown()

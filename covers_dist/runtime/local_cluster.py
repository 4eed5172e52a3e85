"""A loopback-only multi-node Ray cluster on this machine, for benchmarks and fault tests.

Built on ``ray.cluster_utils.Cluster``: a head node and worker nodes as separate Ray node
processes, every process bound to 127.0.0.1, all under one temp dir of the cluster's own. Nodes
can be added and removed while a run uses the cluster (``remove_node`` kills that node's raylet,
object store and worker processes, as a lost machine would). Stop it with :meth:`shutdown`, which
ends exactly the processes it started.

:meth:`LocalCluster.add_isolated_node` adds a node that does not share the driver's disk: its
raylet and every process it starts run in their own mount namespace (``unshare --mount``, root
only) with an empty tmpfs over the given directories (the run directory), as on a cluster
without a shared filesystem. Losing it kills every process in that namespace.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

__all__ = ["LocalCluster", "IsolatedNode"]


class IsolatedNode:
    """A Ray node in its own mount namespace (:meth:`LocalCluster.add_isolated_node`)."""

    def __init__(self, proc: subprocess.Popen, node_id: str, namespace: str, log_path: Path) -> None:
        self.proc, self.node_id, self.namespace, self.log_path = proc, node_id, namespace, log_path

    def pids(self) -> list[int]:
        """Every process in the node's mount namespace (all of them started by the node)."""
        out = []
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    if os.readlink(entry / "ns" / "mnt") == self.namespace:
                        out.append(int(entry.name))
                except OSError:
                    continue
        return out

    def kill(self) -> None:
        """Kill every process of the node at once, as a machine that is lost."""
        for pid in self.pids():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.proc.wait(30)


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
        self._isolated: list[IsolatedNode] = []

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
        if isinstance(node, IsolatedNode):
            node.kill()
            self._isolated.remove(node)
            return
        self.cluster.remove_node(node, allow_graceful=False)

    def add_isolated_node(self, num_cpus: int, hide: list[str | Path], timeout_s: float = 60.0) -> IsolatedNode:
        """A node whose processes see an empty tmpfs over each directory of ``hide`` (they must
        exist): it shares no files there with the driver or the other nodes. Needs root and
        ``unshare`` (util-linux); the caller must be connected to the cluster (``ray.init``)."""
        import ray

        unshare = shutil.which("unshare")
        if unshare is None or os.geteuid() != 0:
            raise RuntimeError("an isolated node needs root and unshare (util-linux): a mount namespace of its own")
        before = {n["NodeID"] for n in ray.nodes()}
        mounts = "".join(f'mount -t tmpfs covers-isolated "${i + 1}" && ' for i in range(len(hide)))
        launcher = [sys.executable, "-m", "covers_dist.runtime.local_cluster", self.address, str(num_cpus), self.temp_dir]
        log_path = Path(self.temp_dir) / f"isolated-node-{len(self._isolated)}.log"
        # sh's positional parameters: $1.. are the directories to hide, the command follows them
        script = f'{mounts}shift {len(hide)} && exec "$@"'
        cmd = [unshare, "--mount", "--propagation", "private", "sh", "-c", script, "sh", *map(str, hide), *launcher]
        with open(log_path, "ab") as log:
            proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            new = [n for n in ray.nodes() if n["Alive"] and n["NodeID"] not in before]
            if new:
                node = IsolatedNode(proc, new[0]["NodeID"], os.readlink(f"/proc/{proc.pid}/ns/mnt"), log_path)
                self._isolated.append(node)
                return node
            if proc.poll() is not None:
                break
            time.sleep(0.2)
        if proc.poll() is None:
            proc.kill()
        tail = log_path.read_text(errors="replace")[-2000:] if log_path.exists() else ""
        raise RuntimeError(f"the isolated node did not join the cluster within {timeout_s:g} s:\n{tail}")

    def _restore(self) -> None:
        private_utils, common_utils = self._modules
        private_utils.write_ray_address, common_utils.reset_ray_address = self._write, self._reset

    def shutdown(self, keep_logs: bool | None = None) -> None:
        """Disconnect this process (if connected), stop every node this cluster started and remove
        the cluster's temp dir (kept with Ray's logs with ``keep_logs``, by default after a failure:
        see :func:`~covers_dist.runtime.ray_setup.shutdown_ray`)."""
        import ray

        from .ray_setup import failing

        keep = failing() if keep_logs is None else keep_logs
        try:
            if ray.is_initialized():
                ray.shutdown()
            for node in list(self._isolated):
                node.kill()
            self.cluster.shutdown()
        finally:
            self._restore()
        if not keep:
            shutil.rmtree(self.temp_dir, ignore_errors=True)

    def __enter__(self) -> "LocalCluster":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.shutdown(keep_logs=exc[0] is not None)


def _serve_node(address: str, num_cpus: int, temp_dir: str) -> None:
    """Run one worker node of the cluster at ``address`` in this process until it is killed
    (what :meth:`LocalCluster.add_isolated_node` starts inside its mount namespace)."""
    import ray._private.node
    import ray._private.parameter

    from .ray_setup import loopback_only

    loopback_only()
    params = ray._private.parameter.RayParams(
        num_cpus=num_cpus, num_gpus=0, node_ip_address="127.0.0.1", temp_dir=temp_dir, gcs_address=address,
        object_store_memory=150 * 1024 * 1024, min_worker_port=0, max_worker_port=0, node_manager_port=0,
        include_log_monitor=False,
    )  # fmt: skip
    params.dashboard_agent_listen_port = None
    ray._private.node.Node(params, head=False, shutdown_at_exit=True, spawn_reaper=True)
    while True:
        time.sleep(3600)


if __name__ == "__main__":
    _serve_node(sys.argv[1], int(sys.argv[2]), sys.argv[3])

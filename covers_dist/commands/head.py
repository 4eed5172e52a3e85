"""``covers-dist head start | env | status | stop``: a local, loopback-only Ray head for ``ray job submit``.

``start`` runs ``ray start --head`` with every process bound to 127.0.0.1
(``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0``, ``--node-ip-address=127.0.0.1``, the dashboard on
127.0.0.1), a temp dir of its own, free ports for Ray's agents, and token authentication with a
token of its own (``STATE_DIR/auth_token``, mode 0600). It records the head in
``STATE_DIR/head.json`` (default ``~/.covers-dist/head``): temp dir, ports, the PIDs of its
processes. ``env`` prints the ``export`` lines a client shell needs (``RAY_ADDRESS``,
``RAY_AUTH_MODE``, ``RAY_AUTH_TOKEN_PATH``). ``stop`` ends exactly this head's processes (those
recorded and any other whose command line names its temp dir, e.g. job drivers), SIGTERM first,
SIGKILL for what is left after a grace period (Ray's gcs_server and raylet ignore SIGTERM), and
never touches another Ray instance: no ``ray stop``.
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ..runtime.processes import running

DEFAULT_STATE_DIR = Path.home() / ".covers-dist" / "head"
NOT_RUNNING = 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("head", help="start, inspect or stop a local loopback-only Ray head (for ray job submit)",
                       description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
                       formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    p.add_argument("action", choices=("start", "env", "status", "stop"), help="what to do")
    p.add_argument("--state-dir", default=os.environ.get("COVERS_HEAD_DIR", str(DEFAULT_STATE_DIR)),
                   help="where the head's record and token live (default: $COVERS_HEAD_DIR or ~/.covers-dist/head)")
    p.add_argument("--num-cpus", type=int, default=2, help="CPUs the head offers (default: 2)")
    p.add_argument("--port", type=int, default=None,
                   help="GCS port (default: 6379, or a free one when 6379 is taken; 0: a free one)")
    p.add_argument("--dashboard-port", type=int, default=None,
                   help="dashboard / job API port (default: 8265, or a free one when 8265 is taken; 0: a free one)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for start or stop (default: 120)")
    p.set_defaults(func=run)


# ---- processes ------------------------------------------------------------------------------------
def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _parent(pid: int) -> int:
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def head_processes(temp_dir: str) -> list[int]:
    """Live processes of the head: those whose command line names ``temp_dir`` (its own, and
    nobody else's) and their descendants (Ray workers retitle themselves, job drivers)."""
    own = os.getpid()
    live = [int(e.name) for e in Path("/proc").iterdir() if e.name.isdigit() and running(int(e.name))]
    found = {p for p in live if p != own and temp_dir in _cmdline(p)}
    parents = {p: _parent(p) for p in live}
    grown = True
    while grown:
        more = {p for p, parent in parents.items() if parent in found and p not in found and p != own}
        found |= more
        grown = bool(more)
    return sorted(found)


def _alive(state: dict[str, Any]) -> list[int]:
    """Recorded PIDs still running this head (a reused PID is no longer one of its processes)."""
    current = set(head_processes(state["temp_dir"]))
    return [p for p in state.get("pids", []) if p in current]


# ---- state ----------------------------------------------------------------------------------------
def _state_file(state_dir: Path) -> Path:
    return state_dir / "head.json"


def load_state(state_dir: Path) -> dict[str, Any] | None:
    f = _state_file(state_dir)
    if not f.is_file():
        return None
    try:
        return json.loads(f.read_text())
    except json.JSONDecodeError as e:
        raise SystemExit(f"covers-dist head: {f} is corrupt ({e}); remove it after checking no head runs") from None


def client_env(state: dict[str, Any]) -> dict[str, str]:
    """What a client (``ray job submit``, ``covers-dist train --address``) needs in its environment."""
    return {
        "RAY_ADDRESS": f"http://127.0.0.1:{state['dashboard_port']}",
        "RAY_AUTH_MODE": "token",
        "RAY_AUTH_TOKEN_PATH": state["token_path"],
    }


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _default_port(requested: int | None, conventional: int) -> int:
    """``requested`` (0: a free one), or ``conventional`` if free, else a free one."""
    if requested is None:
        requested = conventional if _port_free(conventional) else 0
    return requested or _free_port()


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


# ---- actions --------------------------------------------------------------------------------------
def start(args: argparse.Namespace, state_dir: Path) -> int:
    old = load_state(state_dir)
    if old is not None and _alive(old):
        raise SystemExit(
            f"covers-dist head: a head is already running ({old['gcs_address']}, PIDs {_alive(old)}); "
            "stop it first with: covers-dist head stop"
        )
    if args.num_cpus < 1:
        raise SystemExit(f"covers-dist head: --num-cpus must be >= 1, got {args.num_cpus}")
    for name in ("port", "dashboard_port"):
        value = getattr(args, name)
        if value is not None and not 0 <= value <= 65535:
            raise SystemExit(f"covers-dist head: --{name.replace('_', '-')} must be in 0..65535, got {value}")
    # the conventional ports when free; clients find the actual ones with `covers-dist head env`
    port, dash = (_default_port(v, d) for v, d in ((args.port, 6379), (args.dashboard_port, 8265)))
    for name, p in (("--port", port), ("--dashboard-port", dash)):
        if not _port_free(p):
            raise SystemExit(f"covers-dist head: port {p} ({name}) is in use on 127.0.0.1; choose another ({name} 0: any free one)")
    state_dir.mkdir(parents=True, exist_ok=True)
    token = state_dir / "auth_token"
    token.write_text(secrets.token_hex(32))
    os.chmod(token, 0o600)
    temp = tempfile.mkdtemp(prefix="covers-head-", dir="/tmp")  # short: Ray's socket paths live under it
    agent = _free_port()
    ports = {"dashboard-agent-listen-port": agent, "dashboard-agent-grpc-port": _free_port(),
             "runtime-env-agent-port": _free_port(), "metrics-export-port": _free_port(),
             "ray-client-server-port": _free_port()}  # fmt: skip
    env = {**os.environ, "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "token",
           "RAY_AUTH_TOKEN_PATH": str(token)}  # fmt: skip
    env.pop("RAY_ADDRESS", None)
    bindir = str(Path(sys.executable).parent)  # job entrypoints (covers-dist, python) resolve to this install
    env["PATH"] = os.pathsep.join([bindir, *(p for p in env.get("PATH", "").split(os.pathsep) if p and p != bindir)])
    ray_exe = str(Path(bindir) / "ray")
    cmd = [ray_exe, "start", "--head", f"--num-cpus={args.num_cpus}", "--node-ip-address=127.0.0.1",
           f"--port={port}", f"--dashboard-port={dash}", "--dashboard-host=127.0.0.1", "--include-dashboard=true",
           f"--temp-dir={temp}", "--disable-usage-stats", *(f"--{k}={v}" for k, v in ports.items())]  # fmt: skip
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
    state = {"temp_dir": temp, "gcs_address": f"127.0.0.1:{port}", "dashboard_port": dash, "port": port,
             "agent_ports": ports, "token_path": str(token), "started": time.time(), "pids": head_processes(temp)}  # fmt: skip
    _state_file(state_dir).write_text(json.dumps(state, indent=1))
    if done.returncode != 0:
        stop_processes(state, 10.0)
        _state_file(state_dir).unlink(missing_ok=True)
        raise SystemExit(f"covers-dist head: ray start failed:\n{done.stdout[-2000:]}{done.stderr[-2000:]}")
    deadline = time.monotonic() + args.timeout
    while not (_listening(dash) and _listening(agent)):  # the job API and the head's job agent
        if time.monotonic() > deadline:
            stop_processes(state, 10.0)
            _state_file(state_dir).unlink(missing_ok=True)
            raise SystemExit(f"covers-dist head: the dashboard and job agent did not come up within {args.timeout:g} s")
        time.sleep(0.5)
    state["pids"] = head_processes(temp)
    _state_file(state_dir).write_text(json.dumps(state, indent=1))
    print(f"covers-dist head: started {state['gcs_address']} (dashboard and job API http://127.0.0.1:{dash}), "
          f"{len(state['pids'])} processes, temp dir {temp}")  # fmt: skip
    print("client environment (or: eval \"$(covers-dist head env)\"):")
    for k, v in client_env(state).items():
        print(f"  export {k}={v}")
    return 0


def stop_processes(state: dict[str, Any], grace_s: float) -> list[int]:
    """SIGTERM, then SIGKILL after ``grace_s``, to this head's processes; the PIDs ended."""
    pids = sorted(set(_alive(state)) | set(head_processes(state["temp_dir"])))
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 10.0)):
        current = set(head_processes(state["temp_dir"]))
        for pid in pids:
            if pid in current:
                try:
                    os.kill(pid, sig)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline and any(running(p) for p in pids):
            time.sleep(0.2)
        pids = sorted(set(pids) | set(head_processes(state["temp_dir"])))  # children started meanwhile
    return pids


def run(args: argparse.Namespace) -> int:
    state_dir = Path(args.state_dir).expanduser()
    if args.action == "start":
        return start(args, state_dir)
    state = load_state(state_dir)
    if args.action == "stop":
        if state is None:
            print(f"covers-dist head: no head recorded in {state_dir}; nothing to stop", file=sys.stderr)
            return NOT_RUNNING
        ended = stop_processes(state, grace_s=5.0)
        left = head_processes(state["temp_dir"])
        if left:
            raise SystemExit(f"covers-dist head: processes {left} of the head did not stop")
        _state_file(state_dir).unlink(missing_ok=True)
        print(f"covers-dist head: stopped {state['gcs_address']} ({len(ended)} processes)")
        return 0
    alive = _alive(state) if state is not None else []
    if args.action == "env":
        if not alive:
            print(f"covers-dist head: no running head recorded in {state_dir} (start one: covers-dist head start)",
                  file=sys.stderr)  # fmt: skip
            return NOT_RUNNING
        for k, v in client_env(state).items():
            print(f"export {k}={v}")
        return 0
    if not alive:  # status
        print(f"covers-dist head: not running (no live head recorded in {state_dir})")
        return NOT_RUNNING
    print(f"covers-dist head: running {state['gcs_address']}, dashboard and job API http://127.0.0.1:"
          f"{state['dashboard_port']}, PIDs {alive}, temp dir {state['temp_dir']}")  # fmt: skip
    return 0

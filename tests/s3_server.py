"""A real S3 API server on 127.0.0.1 for the tests: moto's server mode, in its own process.

``with s3_server() as s3: s3.uri("bucket/prefix")`` gives a ``runtime.storage`` URI that every
process of the machine (Ray nodes included) reaches; the credentials are placeholders the
server accepts, set in this process's environment (and so inherited by the processes it starts)
for as long as the server runs.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from typing import Iterator

ENV = {
    "AWS_ACCESS_KEY_ID": "covers-test",
    "AWS_SECRET_ACCESS_KEY": "covers-test",
    "AWS_DEFAULT_REGION": "us-east-1",
    "AWS_EC2_METADATA_DISABLED": "true",  # never ask a cloud metadata service for credentials
}


class S3Server:
    def __init__(self, port: int) -> None:
        self.port = port
        self.endpoint = f"127.0.0.1:{port}"

    def uri(self, path: str, port: int | None = None) -> str:
        """``s3://path`` on this server (or through the :class:`Gate` on ``port``); the bucket (the
        first part of ``path``) is created if missing."""
        endpoint = self.endpoint if port is None else f"127.0.0.1:{port}"
        return f"s3://{path}?endpoint_override={endpoint}&scheme=http&region=us-east-1&allow_bucket_creation=true"

    def make_bucket(self, name: str) -> None:
        from covers_dist.storage import Storage

        Storage(self.uri(name)).fs.create_dir(name)


class Gate:
    """A TCP relay on 127.0.0.1 in front of a server: :meth:`close` makes the server go away (new
    connections refused, open ones cut), :meth:`open` brings it back on the same port, with every
    object it held (an outage of the network or of the server's front end, not a lost disk)."""

    def __init__(self, target_port: int) -> None:
        self.target = target_port
        self.port = _free_port()
        self._lock = threading.Lock()
        self._conns: set[socket.socket] = set()
        self._listener: socket.socket | None = None
        self.open()

    def open(self) -> None:
        listener = socket.socket()
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", self.port))
        listener.listen(64)
        self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True).start()

    def close(self) -> None:
        if self._listener is not None:
            self._listener.close()
            self._listener = None
        with self._lock:
            conns, self._conns = self._conns, set()
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)
            conn.close()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:  # closed
                return
            try:
                upstream = socket.create_connection(("127.0.0.1", self.target), timeout=10)
                upstream.settimeout(None)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._conns |= {client, upstream}
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(a: socket.socket, b: socket.socket) -> None:
        try:
            while data := a.recv(65536):
                b.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (a, b):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def s3_server(timeout_s: float = 30.0) -> Iterator[S3Server]:
    port = _free_port()
    old = {k: os.environ.get(k) for k in ENV}
    os.environ.update(ENV)
    # its request log goes to a file: a pipe nobody reads would fill and stall the server
    log = tempfile.TemporaryFile()
    proc = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)], stdout=log, stderr=subprocess.STDOUT
    )
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/moto-api/", timeout=1).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    log.seek(0)
                    raise RuntimeError(f"the S3 server did not start: {log.read()[-2000:].decode(errors='replace')}")
                time.sleep(0.1)
        yield S3Server(port)
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

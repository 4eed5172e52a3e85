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

    def uri(self, path: str) -> str:
        """``s3://path`` on this server; the bucket (the first part of ``path``) is created if missing."""
        return f"s3://{path}?endpoint_override={self.endpoint}&scheme=http&region=us-east-1&allow_bucket_creation=true"

    def make_bucket(self, name: str) -> None:
        from covers_dist.storage import Storage

        Storage(self.uri(name)).fs.create_dir(name)


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

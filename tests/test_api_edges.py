"""HTTP edge cases on a real uvicorn server on 127.0.0.1: the Host allow-list of a server without a
token (DNS rebinding), the connection limit (503 at once), and PNG decoding off the event loop."""

from __future__ import annotations

import socket
import threading

import httpx
import pytest
from api_helpers import STREAM, api_config, filled_service, initial_obs, obs_batch_json

from covers_dist.api import ApiServerThread, LocalSource, create_app
from covers_dist.api import deps as api_deps
from covers_dist.config import ConfigError


@pytest.fixture(scope="module")
def cfg():
    return api_config("clustering.initial_frames=2")


@pytest.fixture(scope="module")
def service(cfg):
    return filled_service(cfg, STREAM[:2])


def _server(cfg, service, *overrides, token=""):
    if overrides:
        cfg = api_config("clustering.initial_frames=2", *overrides)
    return ApiServerThread(create_app(cfg, LocalSource(service), token=token)).start()


def test_a_server_without_a_token_answers_only_for_its_own_host_names(cfg, service):
    with _server(cfg, service) as server, httpx.Client(base_url=server.url, timeout=30) as c:
        port = server.url.rsplit(":", 1)[1]
        for route in ("/healthz", "/v1/policies", "/docs"):
            r = c.get(route, headers={"Host": f"rebound.example:{port}"})
            assert r.status_code == 400, (route, r.status_code)
            assert "Host header 'rebound.example:" in r.json()["detail"] and "api.allowed_hosts" in r.json()["detail"]
        for host in (f"127.0.0.1:{port}", f"localhost:{port}", "localhost", f"[::1]:{port}", "LOCALHOST."):
            assert c.get("/v1/policies", headers={"Host": host}).status_code == 200, host
    with _server(cfg, service, "api.allowed_hosts=[covers.internal]") as server, httpx.Client(base_url=server.url) as c:
        assert c.get("/healthz", headers={"Host": "covers.internal:8000"}).status_code == 200
        assert c.get("/healthz", headers={"Host": "localhost"}).status_code == 400  # the list replaces the default
    with _server(cfg, service, "api.allowed_hosts=['*']") as server, httpx.Client(base_url=server.url) as c:
        assert c.get("/healthz", headers={"Host": "anything.example"}).status_code == 200


def test_a_server_with_a_token_answers_any_host_but_only_with_the_token(cfg, service):
    with _server(cfg, service, token="t0k") as server, httpx.Client(base_url=server.url, timeout=30) as c:
        assert c.get("/v1/policies", headers={"Host": "api.example"}).status_code == 401
        ok = c.get("/v1/policies", headers={"Host": "api.example", "Authorization": "Bearer t0k"})
        assert ok.status_code == 200


def test_bad_allowed_hosts_are_refused():
    for bad in ("[]", "['not a host']", "['ok.example', '-bad']"):
        with pytest.raises(ConfigError, match="api.allowed_hosts"):
            api_config(f"api.allowed_hosts={bad}")


def test_connections_past_the_limit_are_answered_503_at_once(cfg, service):
    with _server(cfg, service, "api.max_connections=3") as server:
        host, port = server.url.removeprefix("http://").rsplit(":", 1)
        held = []
        try:
            for _ in range(2):  # two idle keep-alive connections and the next one reach the limit
                s = socket.create_connection((host, int(port)), timeout=10)
                s.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                assert s.recv(4096).startswith(b"HTTP/1.1 200")
                held.append(s)
            r = httpx.get(f"{server.url}/healthz", timeout=10)
            assert r.status_code == 503
        finally:
            for s in held:
                s.close()
        for _ in range(50):  # the server notices the closed connections
            if httpx.get(f"{server.url}/healthz", timeout=10).status_code == 200:
                break
            threading.Event().wait(0.1)
        else:
            raise AssertionError("still 503 after the held connections closed")


def test_png_decoding_runs_off_the_event_loop(cfg, service, monkeypatch):
    """A what-if request whose decoding is held up does not hold up the server: /healthz answers
    while it decodes (with decoding on the event loop, nothing would answer until it ended)."""
    real = api_deps.decode_observations
    started, release = threading.Event(), threading.Event()

    def slow_decode(observations, layout):
        started.set()
        release.wait(30)
        return real(observations, layout)

    monkeypatch.setattr(api_deps, "decode_observations", slow_decode)
    body = {"observations": obs_batch_json(initial_obs(cfg, "reach", "e", [1, 2]))}
    with _server(cfg, service) as server:
        result: dict = {}
        post = threading.Thread(
            target=lambda: result.update(r=httpx.post(f"{server.url}/v1/assignments/what-if", json=body, timeout=60))
        )
        post.start()
        try:
            assert started.wait(30)
            assert httpx.get(f"{server.url}/healthz", timeout=5).status_code == 200
        finally:
            release.set()
            post.join(60)
        assert result["r"].status_code == 200, result["r"].text

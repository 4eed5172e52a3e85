"""Malformed requests get a 4xx with a message naming the problem (never a 500); size limits and
bearer-token auth. A real uvicorn server on 127.0.0.1 and a real httpx client."""

from __future__ import annotations

import base64
import io

import httpx
import numpy as np
import pytest
from api_helpers import STREAM, api_config, filled_service, initial_obs, obs_batch_json
from PIL import Image

from covers_dist.api import TOKEN_ENV, ApiServerThread, LocalSource, create_app

TOKEN = "s3cret-token"


@pytest.fixture(scope="module")
def cfg():
    return api_config("clustering.initial_frames=2")


@pytest.fixture(scope="module")
def service(cfg):
    return filled_service(cfg, STREAM[:3])


@pytest.fixture(scope="module")
def client(cfg, service):
    with ApiServerThread(create_app(cfg, LocalSource(service), token="")).start() as server:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            yield c


@pytest.fixture(scope="module")
def good(cfg):
    return obs_batch_json(initial_obs(cfg, "reach", "e", [1, 2]))


def _png(size: int, mode: str = "RGB") -> str:
    buf = io.BytesIO()
    Image.new(mode, (size, size)).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


def _with_image(obs: dict, image: object) -> dict:
    return {**obs, "image": image}


def _expect(r: httpx.Response, status: int, *words: str) -> None:
    assert r.status_code == status, (r.status_code, r.text)
    detail = r.json()["detail"]
    assert isinstance(detail, str) and detail
    for w in words:
        assert w in detail, (w, detail)


def test_malformed_observations(client, good):
    o = good[0]
    cases = [
        (_with_image(o, {"shape": [32, 32], "data": [0] * 3072}), "expected [32, 32, 3]"),
        (_with_image(o, {"shape": [16, 16, 3], "data": [0] * 768}), "expected [32, 32, 3]"),
        (_with_image(o, {"shape": [32, 32, 3], "data": [0] * 100}), "data has 100 values"),
        (_with_image(o, {"shape": [32, 32, 3], "data": [0.5] * 3072}), "data.0"),
        (_with_image(o, {"shape": [32, 32, 3], "data": [256] * 3072}), "less than or equal to 255"),
        (_with_image(o, {"shape": [32, 32, 3], "data": [-1] * 3072}), "greater than or equal to 0"),
        (_with_image(o, {"shape": [32, 32, 3], "data": ["7"] * 3072}), "data.0"),
        (_with_image(o, {"png_base64": "not base64!"}), "not valid base64"),
        (_with_image(o, {"png_base64": base64.b64encode(b"GIF89a....").decode()}), "does not hold a PNG"),
        (_with_image(o, {"png_base64": _png(32)[:60]}), "not a readable PNG"),
        (_with_image(o, {"png_base64": _png(64)}), "64x64 pixels, expected 32x32"),
        (_with_image(o, {"png_base64": _png(32), "shape": [32, 32, 3]}), "image"),
        (_with_image(o, "pixels"), "image"),
        ({**o, "proprio": [0.0, 1.0]}, "proprio has 2 values, expected 4"),
        ({**o, "proprio": ["a", 1, 2, 3]}, "proprio.0"),
        ({**o, "proprio": [1e300, 0, 0, 0]}, "fit in float32"),
        ({"proprio": o["proprio"]}, "image"),
        ({**o, "extra": 1}, "extra"),
    ]
    for obs, words in cases:
        _expect(client.post("/v1/act", json={"observation": obs}), 422, words)
        _expect(client.post("/v1/assignments/what-if", json={"observations": [obs, good[1]]}), 422, words)


def test_malformed_bodies(client, good):
    nan_body = b'{"observation": {"image": %s, "proprio": [NaN, 0, 0, 0]}}' % (
        str(good[0]["image"]).replace("'", '"').encode()
    )
    _expect(client.post("/v1/act", content=nan_body, headers={"content-type": "application/json"}), 422, "proprio")
    _expect(client.post("/v1/act", content=b"{bad json", headers={"content-type": "application/json"}), 422, "JSON")
    _expect(client.post("/v1/act", content=b"[1, 2]", headers={"content-type": "application/json"}), 422)
    _expect(client.post("/v1/act", content=b"hello"), 422, "JSON object")
    _expect(client.post("/v1/act", json={}), 422, "observation")
    _expect(client.post("/v1/act", json={"observation": good[0], "policy_id": -1}), 422, "policy_id")
    _expect(client.post("/v1/act", json={"observation": good[0], "policy_id": "1"}), 422, "policy_id")
    _expect(client.post("/v1/act", json={"observation": good[0], "deterministic": "maybe"}), 422, "deterministic")
    what_if = "/v1/assignments/what-if"
    _expect(client.post(what_if, json={"observations": []}), 422, "observations")
    _expect(client.post(what_if, json={"observations": good[:1]}), 422, "multiple of clustering.initial_frames=2")
    _expect(client.post(what_if, json={"observations": good * 5}), 422, "at most api.max_batch=8")


def test_unknown_ids_and_bad_query_params(client, good):
    _expect(client.get("/v1/policies/999"), 404, "policy 999 does not exist")
    _expect(client.get("/v1/policies/abc"), 422, "policy_id")
    _expect(client.get("/v1/policies/-3"), 422, "policy_id")
    _expect(client.post("/v1/act", json={"observation": good[0], "policy_id": 999}), 404, "policy 999")
    _expect(client.post("/v1/act", json={"observation": good[0], "policy_id": 2**70}), 404)
    for params, word in (({"since": -1}, "since"), ({"limit": 0}, "limit"), ({"limit": 5000}, "limit"),
                         ({"limit": "ten"}, "limit"), ({"since": "1.5"}, "since")):
        _expect(client.get("/v1/assignments", params=params), 422, word)
    assert client.get("/v1/nothing-here").status_code == 404
    assert client.delete("/v1/policies").status_code == 405


def test_body_size_limit(client, cfg):
    big = b"x" * (cfg.api.max_body_bytes + 1)
    _expect(client.post("/v1/act", content=big, headers={"content-type": "application/json"}), 413, "max_body_bytes")

    def chunks():
        for _ in range(40):
            yield b" " * 10_000

    headers = {"content-type": "application/json"}
    _expect(client.post("/v1/assignments/what-if", content=chunks(), headers=headers), 413)
    # the server still answers afterwards
    assert client.get("/healthz").status_code == 200


@pytest.mark.parametrize("from_env", [False, True], ids=["config", "env"])
def test_bearer_token(cfg, service, good, monkeypatch, from_env):
    if from_env:
        monkeypatch.setenv(TOKEN_ENV, TOKEN)
        app = create_app(cfg, LocalSource(service))
    else:
        monkeypatch.delenv(TOKEN_ENV, raising=False)
        app = create_app(api_config("clustering.initial_frames=2", f"api.token={TOKEN}"), LocalSource(service))
    with ApiServerThread(app).start() as server, httpx.Client(base_url=server.url, timeout=30) as c:
        auth = {"Authorization": f"Bearer {TOKEN}"}
        for path in ("/healthz", "/readyz", "/openapi.json"):
            assert c.get(path).status_code == 200, path
        paths = ("/v1/policies", "/v1/policies/0", "/v1/assignments/latest", "/v1/assignment", "/v1/assignments")
        for path in (*paths, "/v1/metrics", "/metrics"):
            r = c.get(path)
            _expect(r, 401, "bearer token")
            assert r.headers["www-authenticate"] == "Bearer"
            _expect(c.get(path, headers={"Authorization": "Bearer wrong"}), 401)
            _expect(c.get(path, headers={"Authorization": TOKEN}), 401)
            assert c.get(path, headers=auth).status_code == 200, path
        _expect(c.post("/v1/act", json={"observation": good[0]}), 401)
        assert c.post("/v1/act", json={"observation": good[0]}, headers=auth).status_code == 200
        _expect(c.post("/v1/assignments/what-if", json={"observations": good}), 401)
        assert c.post("/v1/assignments/what-if", json={"observations": good}, headers=auth).status_code == 200


def test_no_token_means_open(client, good):
    assert client.get("/v1/policies").status_code == 200
    assert client.post("/v1/act", json={"observation": good[0]}).status_code == 200


def test_never_a_server_error(client):
    text = client.get("/metrics").text
    statuses = [line for line in text.splitlines() if line.startswith("covers_api_requests_total")]
    assert statuses and not [s for s in statuses if 'status="5' in s]
    assert np.all([s.split()[-1] != "0.0" for s in statuses])


def test_serve_cli_fails_clearly(tmp_path):
    from covers_dist.cli import main

    with pytest.raises(SystemExit, match="is not a run directory"):
        main(["serve", "--run-dir", str(tmp_path)])
    (tmp_path / "config.yaml").write_text("name: empty\n")
    with pytest.raises(SystemExit, match="no valid checkpoint"):
        main(["serve", "--run-dir", str(tmp_path), "--port", "0"])
    with pytest.raises(SystemExit, match="no Ray cluster answers at 127.0.0.1:1"):
        main(["serve", "--address", "127.0.0.1:1", "--name", "nothing"])
    assert main(["serve", "--run-dir", str(tmp_path), "--set", "runtime.num_workers=3"]) == 2


def test_serve_checkpoint_flag_is_a_deprecated_alias_of_run_dir(tmp_path, capsys):
    from covers_dist.cli import main

    with pytest.raises(SystemExit, match="is not a run directory"):
        main(["serve", "--checkpoint", str(tmp_path)])
    assert "--checkpoint is deprecated, use --run-dir" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # one or the other
        main(["serve", "--checkpoint", str(tmp_path), "--run-dir", str(tmp_path)])

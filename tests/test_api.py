"""The HTTP service against a real clustering service in this process, through a real uvicorn
server on 127.0.0.1 and a real httpx client: every endpoint's answers match the service."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from api_helpers import (
    STREAM,
    api_config,
    filled_service,
    initial_obs,
    obs_batch_json,
    policy_weights,
    wait_until,
)
from prometheus_client.parser import text_string_to_metric_families

from covers_dist.api import ApiServerThread, LocalSource, create_app
from covers_dist.runtime.clustering_service import ClusteringService


@pytest.fixture(scope="module")
def cfg():
    return api_config()


@pytest.fixture(scope="module")
def service(cfg):
    return filled_service(cfg, STREAM)


@pytest.fixture(scope="module")
def client(cfg, service):
    with ApiServerThread(create_app(cfg, LocalSource(service), token="")).start() as server:
        assert server.url.startswith("http://127.0.0.1:")
        with httpx.Client(base_url=server.url, timeout=30) as c:
            yield c


def test_health_and_readiness(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["ready"] is True and ready.json()["source"] == "local"


def test_policies_match_the_bank(client, service):
    body = client.get("/v1/policies").json()
    summary = service.summary()
    assert body["num_policies"] == len(service.bank) >= 2, "the low threshold should make several policies"
    assert body["current_policy_id"] == service.current_policy_id()
    assert body["metric"] == "wasserstein" and body["threshold"] == pytest.approx(0.1)
    for got, want in zip(body["policies"], summary["policies"], strict=True):
        for key in ("policy_id", "created_at_episode", "episodes_assigned", "buffer_size", "group_histogram"):
            assert got[key] == want[key], key
        assert got["last_success"] == want["last_success"] and got["last_return"] == want["last_return"]
        names = {summary["group_names"][g]: n for g, n in want["group_histogram"].items()}
        assert got["group_histogram_by_name"] == names
    one = client.get("/v1/policies/1")
    assert one.status_code == 200 and one.json() == body["policies"][1]
    assert sum(sum(p["group_histogram"].values()) for p in body["policies"]) == 4 * len(STREAM)


def test_current_assignment_and_history(client, service):
    cur = client.get("/v1/assignments/latest").json()
    assert cur["current_policy_id"] == service.current_policy_id()
    assert cur["num_assignments"] == service.num_assignments() == len(STREAM)
    last = service.last_assignment()
    assert cur["last"]["index"] == last["index"] and cur["last"]["decision"] == last["decision"]
    assert cur["last"]["distances"] == pytest.approx(last["distances"])
    history = service.assignments(0, 100)
    page = client.get("/v1/assignments", params={"since": 1, "limit": 2}).json()
    assert (page["total"], page["since"], page["limit"], page["next_since"]) == (len(STREAM), 1, 2, 3)
    assert [r["index"] for r in page["items"]] == [1, 2]
    assert page["items"][0]["episode_indices"] == history[1]["episode_indices"]
    assert page["items"][1]["true_groups"] == history[2]["true_groups"]
    tail = client.get("/v1/assignments", params={"since": 3, "limit": 10}).json()
    assert [r["index"] for r in tail["items"]] == [3, 4] and tail["next_since"] is None
    assert client.get("/v1/assignments", params={"since": 99}).json()["items"] == []
    assert [r["decision"] for r in client.get("/v1/assignments").json()["items"]] == [h["decision"] for h in history]


def test_metrics_json_and_prometheus(client, service):
    m = client.get("/v1/metrics").json()
    want = service.metrics()
    assert m["num_policies"] == want["num_policies"] and m["current_policy_id"] == want["current_policy_id"]
    assert m["ari"] == pytest.approx(want["ari"]) and m["policy_counts"] == want["policy_counts"]
    assert m["episodes"] == 4 * len(STREAM) and m["iteration"] == len(STREAM)
    assert m["success"] == {"push": 0.5} and m["returns"] == {"push": 12.5}  # the latest reported row
    assert m["progress"]["ari"] is None  # NaN travels as null
    text = client.get("/metrics")
    assert text.status_code == 200 and text.headers["content-type"].startswith("text/plain")
    families = {f.name: f for f in text_string_to_metric_families(text.text)}
    assert families["covers_policies"].type == "gauge"
    assert families["covers_policies"].samples[0].value == want["num_policies"]
    for counter in ("covers_episodes", "covers_env_steps", "covers_iterations", "covers_policy_episodes"):
        assert families[counter].type == "counter", counter
        assert all(s.name == f"{counter}_total" for s in families[counter].samples), counter
    assert families["covers_episodes"].samples[0].value == 4 * len(STREAM)
    assert families["covers_iterations"].samples[0].value == len(STREAM)
    assert {s.labels["policy_id"] for s in families["covers_policy_episodes"].samples} == {
        str(p) for p in service.bank.policy_ids
    }
    info = families["covers_current_policy_info"].samples
    assert [(s.labels, s.value) for s in info] == [({"policy_id": str(want["current_policy_id"])}, 1.0)]
    assert families["covers_success_ratio"].samples[0].labels == {"task": "push"}
    assert families["covers_success_ratio"].samples[0].value == 0.5
    # no rate gauges, no ids as values: speeds come from rate() over the counters
    assert not {"covers_env_steps_per_second", "covers_current_policy_id", "covers_num_policies"} & set(families)
    served = [s for s in families["covers_api_requests"].samples if s.name == "covers_api_requests_total"]
    assert any(s.labels["route"] == "/v1/metrics" and s.labels["status"] == "200" for s in served)


def test_every_exported_metric_is_documented(client):
    """docs/guide/api.md's metrics table names every family /metrics exports, with its type."""
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "guide" / "api.md").read_text()
    table = dict(re.findall(r"^\| `(covers_[a-z_]+)(?:\{[^}]*\})?` \| (\w+) \|", doc, re.M))
    client.get("/v1/metrics")
    families = list(text_string_to_metric_families(client.get("/metrics").text))
    assert families
    for f in families:
        if f.name.endswith("_created"):  # prometheus_client's creation time of a documented counter or histogram
            base = f.name[: -len("_created")]
            assert f"{base}_total" in table or base in table, f.name
            continue
        exposed = f"{f.name}_total" if f.type == "counter" else f.name
        assert table.get(exposed) == f.type, (exposed, f.type)


def test_deprecated_paths_still_answer_and_say_so(client):
    new = client.get("/v1/assignments/latest")
    old = client.get("/v1/assignment")
    assert old.status_code == new.status_code == 200
    # the same answer; `as_of` is when the service last refreshed its snapshot, which can fall between the two
    assert {**old.json(), "as_of": None} == {**new.json(), "as_of": None}
    assert old.headers["deprecation"] == "true" and "deprecation" not in new.headers
    assert old.headers["link"] == '</v1/assignments/latest>; rel="successor-version"'
    bad = client.post("/v1/assign", json={"observations": []})
    assert bad.status_code == 422 and bad.headers["deprecation"] == "true"
    assert bad.headers["link"] == '</v1/assignments/what-if>; rel="successor-version"'
    ops = client.get("/openapi.json").json()["paths"]
    assert ops["/v1/assignment"]["get"]["deprecated"] is True and ops["/v1/assign"]["post"]["deprecated"] is True
    assert "deprecated" not in ops["/v1/assignments/latest"]["get"]
    assert "deprecated" not in ops["/v1/assignments/what-if"]["post"]


@pytest.mark.parametrize("png", [True, False], ids=["png", "array"])
def test_what_if_matches_the_bank_and_changes_nothing(client, service, cfg, png):
    obs = initial_obs(cfg, "push", "r3", [500, 501, 502])
    before = (service.num_assignments(), service.summary()["policies"])
    r = client.post("/v1/assignments/what-if", json={"observations": obs_batch_json(obs, png=png)})
    assert r.status_code == 200, r.text
    want = service.bank.what_if(obs).to_dict()
    got = r.json()
    assert (got["policy_id"], got["decision"], got["new"]) == (want["policy_id"], want["decision"], want["new"])
    assert got["distances"] == pytest.approx(want["distances"], rel=1e-6)
    assert got["num_observations"] == 3
    assert (service.num_assignments(), service.summary()["policies"]) == before


def test_act_matches_the_policy_network(client, service, cfg):
    obs = initial_obs(cfg, "avoid", "r", [900])
    body = {"observation": obs_batch_json(obs)[0]}
    for pid in (None, 0, 1):
        r = client.post("/v1/act", json={**body, "policy_id": pid})
        assert r.status_code == 200, r.text
        got = r.json()
        expect_pid = service.current_policy_id() if pid is None else pid
        action, _, value = service.models[expect_pid].act(obs, deterministic=True)
        assert got["policy_id"] == expect_pid and got["deterministic"] is True
        np.testing.assert_allclose(got["action"], action[0], rtol=1e-5, atol=1e-6)
        assert got["value"] == pytest.approx(float(value[0]), rel=1e-5, abs=1e-6)
    sampled = client.post("/v1/act", json={**body, "deterministic": False}).json()
    assert len(sampled["action"]) == 2 and sampled["deterministic"] is False


def test_snapshot_follows_new_assignments(cfg):
    service = filled_service(cfg, STREAM[:2])
    with ApiServerThread(create_app(cfg, LocalSource(service), token="")).start() as server:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            assert c.get("/v1/assignments/latest").json()["num_assignments"] == 2
            obs = initial_obs(cfg, "reach", "r2", [8, 9, 10, 11])
            weights = {pid: (1, policy_weights(cfg, pid)) for pid in service.models}
            record = service.assign(2, obs, [8, 9, 10, 11], [0] * 4, weights)
            page = wait_until(lambda: (p := c.get("/v1/assignments").json())["total"] == 3 and p, timeout_s=5)
            assert page["items"][-1]["policy_id"] == record["policy_id"]
            assert c.get("/v1/assignments/latest").json()["last"]["index"] == 2


def test_a_merged_policy_is_served_as_retired(cfg):
    """After the bank merges a policy into another, /v1/policies lists it under ``retired`` with
    the merge, counts it in ``policies_created``, and no longer serves it as a policy."""
    service = filled_service(cfg, STREAM)
    created = len(service.bank)
    assert created >= 2
    young = max(service.bank.policy_ids)
    with service._lock:
        merge = service.bank.merge(young, 0, distance=0.5)
    with ApiServerThread(create_app(cfg, LocalSource(service), token="")).start() as server:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            body = wait_until(lambda: (b := c.get("/v1/policies").json())["num_policies"] == created - 1 and b, timeout_s=5)
            assert body["policies_created"] == created
            assert [p["policy_id"] for p in body["retired"]] == [young] and body["retired"][0]["merged_into"] == 0
            assert body["merges"] == [merge]
            assert young not in [p["policy_id"] for p in body["policies"]]
            assert c.get(f"/v1/policies/{young}").status_code == 404


def test_empty_bank(cfg):
    service = ClusteringService(cfg)
    with ApiServerThread(create_app(cfg, LocalSource(service), token="")).start() as server:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            assert c.get("/v1/policies").json()["policies"] == []
            cur = c.get("/v1/assignments/latest").json()
            assert cur["last"] is None and cur["current_policy_id"] is None and cur["num_assignments"] == 0
            assert c.get("/v1/metrics").json()["ari"] is None
            one = obs_batch_json(initial_obs(cfg, "reach", "e", [1]))
            r = c.post("/v1/assignments/what-if", json={"observations": one})
            assert r.status_code == 409 and "empty" in r.json()["detail"]
            r = c.post("/v1/act", json={"observation": one[0]})
            assert r.status_code == 404 and "no current policy" in r.json()["detail"]


def test_binding_beyond_loopback_needs_a_token(cfg, service):
    """0.0.0.0 without a token is refused before anything binds; with a token the server is made
    (not started here: tests bind loopback only), and loopback needs none."""
    from covers_dist.config import ConfigError

    with pytest.raises(ConfigError, match=r"api.host='0.0.0.0'.*no token.*api.token or COVERS_API_TOKEN"):
        ApiServerThread(create_app(cfg, LocalSource(service), token=""), host="0.0.0.0")
    with pytest.raises(ConfigError, match="no token"):
        ApiServerThread(create_app(cfg, LocalSource(service), token=""), host="::")
    ApiServerThread(create_app(cfg, LocalSource(service), token="s3cret"), host="0.0.0.0")
    for host in ("127.0.0.1", "::1", "localhost"):
        ApiServerThread(create_app(cfg, LocalSource(service), token=""), host=host)

"""The HTTP service against a training run on Ray (ray.init(num_cpus=2), loopback only) while it
trains, through the named clustering actor; then against the run's saved checkpoint.

Training steps run in a background thread of this process (the same Trainer the CLI runs), the
API server reads the actor it finds by name, and a real httpx client checks every endpoint.
"""

from __future__ import annotations

import threading
from dataclasses import replace

import httpx
import numpy as np
import pytest
from api_helpers import initial_obs, obs_batch_json, smoke_config, wait_until

from covers_dist.api import (
    ApiServerProcess,
    ApiServerThread,
    RaySource,
    create_app,
    load_checkpoint_source,
    start_api_server,
)
from covers_dist.envs import suite_layout
from covers_dist.models import build_actor_critic
from covers_dist.runtime.actors import clustering_actor_name
from covers_dist.runtime.driver import Trainer

# iterations the live run trains in the background (after its first): enough for the tests to see
# it progress and recall (from the 3rd on every iteration recalls); more would only take the CPU
# from the tests running beside it
MAX_STEPS = 6


@pytest.fixture(scope="module")
def live(ray_local, tmp_path_factory):
    """A smoke-config training run stepping in the background, and an API server reading it."""
    run_dir = tmp_path_factory.mktemp("api-live")
    cfg = smoke_config(
        "name=api-live",
        f"runtime.run_dir={run_dir}",
        "runtime.total_env_steps=1000000",
        "api.refresh_s=0.2",
        "api.request_timeout_s=5",
        "network.channels=[2,4]",  # a narrow network: every actor builds it, the endpoints do not care
        "network.hidden=8",
        "env.tasks=[reach,push]",  # two groups, one iteration each: the first recall comes at the 3rd
        "env.episodes_per_task=16",
        "runtime.num_workers=1",  # one actor fewer to start; the endpoints read the clustering actor
    )
    trainer = Trainer(cfg, log=lambda *_: None)
    trainer.start_policy(0)
    stop, lock = threading.Event(), threading.Lock()

    def one_step() -> None:
        with lock:
            trainer.backend.call_clustering("report", trainer.step())

    one_step()

    def loop() -> None:
        for _ in range(MAX_STEPS):
            if stop.is_set():
                return
            one_step()
            # a pause with the lock free: a test waiting for it gets it here (threading.Lock is not
            # fair: without the pause this thread takes it back at once, and the test waits for the
            # whole loop)
            stop.wait(0.2)

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    source = RaySource.connect(clustering_actor_name(cfg), timeout_s=cfg.api.request_timeout_s)
    server = ApiServerThread(create_app(cfg, source, token="")).start()
    client = httpx.Client(base_url=server.url, timeout=60)
    state = {"cfg": cfg, "trainer": trainer, "stop": stop, "thread": thread, "lock": lock, "client": client}
    yield state
    stop.set()
    thread.join(120)
    client.close()
    server.stop()
    trainer.close()


def _actor(live, method, *args):
    return live["trainer"].backend.call_clustering(method, *args)


def _learner_action(live, policy_id, obs):
    cfg = live["cfg"]
    _, weights = live["trainer"].backend.call_learner(policy_id, "weights")
    model = build_actor_critic(cfg.network, suite_layout(cfg.env.suite, cfg.env.image_size))
    model.set_weights(weights)
    return model.eval().act(obs, deterministic=True)[0][0]


def test_every_endpoint_while_training(live):
    c = live["client"]
    assert c.get("/readyz").json()["source"] == "ray"
    first = c.get("/v1/metrics").json()
    later = wait_until(lambda: (m := c.get("/v1/metrics").json())["env_steps"] > first["env_steps"] and m, 120)
    assert later["iteration"] > first["iteration"] and later["episodes"] > first["episodes"]
    assert later["env_steps_per_s"] is None or later["env_steps_per_s"] > 0
    assert set(later["success"]) <= set(live["cfg"].env.tasks) and later["success"]
    policies = c.get("/v1/policies").json()
    assert policies["num_policies"] >= 1 and [p["policy_id"] for p in policies["policies"]] == list(
        range(policies["num_policies"])
    )
    assert c.get(f"/v1/policies/{policies['policies'][-1]['policy_id']}").status_code == 200
    assert c.get("/v1/policies/999").status_code == 404
    cur = c.get("/v1/assignments/latest").json()
    assert cur["last"] is not None and cur["last"]["policy_id"] in {p["policy_id"] for p in policies["policies"]}
    page = c.get("/v1/assignments", params={"limit": 1000}).json()
    assert page["total"] >= cur["num_assignments"] >= 2
    actor_history = _actor(live, "assignments", 0, page["total"])
    assert [r["episode_indices"] for r in page["items"]] == [r["episode_indices"] for r in actor_history]
    assert "covers_env_steps_total " in c.get("/metrics").text


def _paused_after_a_recall(live):
    """Hold the training lock at a moment when the latest assignment recalled a policy: the
    clustering actor then has weights for every policy (a new one gets them one step later)."""
    def attempt():
        live["lock"].acquire()
        if _actor(live, "last_assignment")["decision"] == "recall":
            return True
        live["lock"].release()
        return False

    wait_until(attempt, 180, every_s=0.5)


def test_what_if_and_act_while_training(live):
    c, cfg = live["client"], live["cfg"]
    obs = initial_obs(cfg, "push", "r2f", [7001, 7002])
    one = obs_batch_json(obs)[0]
    _paused_after_a_recall(live)
    try:
        r = c.post("/v1/assignments/what-if", json={"observations": obs_batch_json(obs)})
        assert r.status_code == 200, r.text
        want = _actor(live, "what_if", obs)
        assert (r.json()["policy_id"], r.json()["decision"]) == (want["policy_id"], want["decision"])
        assert r.json()["distances"] == pytest.approx(want["distances"])
        ids = [p["policy_id"] for p in c.get("/v1/policies").json()["policies"]]
        for pid in [None, *ids]:
            r = c.post("/v1/act", json={"observation": one, "policy_id": pid})
            assert r.status_code == 200, r.text
            want = _actor(live, "act", obs, pid, True)
            assert r.json()["policy_id"] == want["policy_id"]
            np.testing.assert_allclose(r.json()["action"], want["action"][0], rtol=1e-5, atol=1e-6)
        r = c.post("/v1/act", json={"observation": one, "policy_id": 999})
        assert r.status_code == 404 and "policy 999" in r.json()["detail"]
    finally:
        live["lock"].release()


def test_served_from_its_own_process(live):
    """start_api_server with the actor handle: `covers-dist serve --address` in a child process."""
    cfg = live["cfg"]
    handle = start_api_server(replace(cfg, api=replace(cfg.api, port=0)), live["trainer"].backend.clustering)
    try:
        with httpx.Client(base_url=handle.url, timeout=60) as c:
            assert wait_until(lambda: c.get("/readyz").status_code == 200, 60)
            cur = c.get("/v1/assignments/latest").json()
            assert cur["num_assignments"] >= 1 and cur["current_policy_id"] is not None
            assert c.get("/v1/policies").json()["num_policies"] >= 1
    finally:
        handle.stop()
    assert handle.proc.poll() is not None


def test_saved_checkpoint_serves_the_same_bank(live):
    live["stop"].set()
    live["thread"].join(120)
    with live["lock"]:
        ckpt = live["trainer"].checkpoint()
    summary = _actor(live, "summary")
    source, run_cfg, path = load_checkpoint_source(live["cfg"].runtime.run_dir)
    assert path == ckpt and run_cfg.name == "api-live"
    obs = initial_obs(live["cfg"], "avoid", "r3", [42])
    with ApiServerThread(create_app(run_cfg, source, token="")).start() as server:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            saved = c.get("/v1/policies").json()
            assert [p["episodes_assigned"] for p in saved["policies"]] == [
                p["episodes_assigned"] for p in summary["policies"]
            ]
            assert saved["current_policy_id"] == summary["current_policy_id"]
            assert c.get("/v1/assignments").json()["total"] == summary["assignments"]
            for p in summary["policies"]:  # the saved weights act exactly like the learners' own
                body = {"observation": obs_batch_json(obs)[0], "policy_id": p["policy_id"]}
                got = c.post("/v1/act", json=body).json()
                want = _learner_action(live, p["policy_id"], obs)
                np.testing.assert_allclose(got["action"], want, rtol=1e-5, atol=1e-6)
            assert c.get("/v1/metrics").json()["episodes"] == _actor(live, "metrics")["progress"]["episodes"]


@pytest.mark.slow
def test_serve_cli_on_the_checkpoint(live):
    """`covers-dist serve --run-dir RUN_DIR` in its own process."""
    live["stop"].set()
    live["thread"].join(120)
    with live["lock"]:
        live["trainer"].checkpoint()
    summary = _actor(live, "summary")
    cfg = replace(live["cfg"], api=replace(live["cfg"].api, port=0, token="cli-token"))
    with ApiServerProcess(["--run-dir", cfg.runtime.run_dir], cfg).start() as server:
        with httpx.Client(base_url=server.url, timeout=60, headers={"Authorization": "Bearer cli-token"}) as c:
            assert httpx.get(f"{server.url}/v1/policies").status_code == 401
            saved = c.get("/v1/policies").json()
            assert saved["num_policies"] == summary["num_policies"]
            obs = obs_batch_json(initial_obs(cfg, "reach", "f", [3]))
            assert c.post("/v1/act", json={"observation": obs[0], "policy_id": 0}).status_code == 200
            assert c.post("/v1/assignments/what-if", json={"observations": obs}).json()["num_observations"] == 1


def test_the_next_policys_learner_is_started_ahead(live):
    """runtime.learner_ahead (on by default): the learner of the policy the bank would create next is
    already running (tests/test_pipeline.py: with it off, none is)."""
    with live["lock"]:
        trainer = live["trainer"]
        assert trainer.backend.spare_learners() == [max(trainer.weights.versions) + 1]


def test_lost_actor_gives_503_not_500(live):
    import ray

    c = live["client"]
    ray.kill(live["trainer"].backend.clustering, no_restart=True)
    one = obs_batch_json(initial_obs(live["cfg"], "reach", "e", [1]))[0]
    r = c.post("/v1/act", json={"observation": one})
    assert r.status_code == 503 and "clustering actor" in r.json()["detail"]
    assert c.get("/v1/assignments/latest").status_code == 200  # the last snapshot is still served
    assert wait_until(lambda: c.get("/readyz").status_code == 503, 30)


def test_a_process_joined_to_one_cluster_refuses_another_address(ray_local):
    """``serve --address`` in a process already connected to Ray names the address that does not
    answer, and refuses one that differs from the cluster it is connected to, rather than quietly
    looking for the actor in the wrong cluster; the address it is on (or ``localhost:``) works."""
    from covers_dist.api.sources import SourceUnavailable, connect_ray

    current = ray_local.get_runtime_context().gcs_address
    with pytest.raises(SourceUnavailable, match="no Ray cluster answers at 127.0.0.1:1"):
        connect_ray("127.0.0.1:1")
    assert connect_ray(current) is ray_local and connect_ray(current.replace("127.0.0.1:", "localhost:")) is ray_local
    assert connect_ray(None) is ray_local

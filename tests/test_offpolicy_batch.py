"""A batch acted by one policy and assigned to another: the assigned policy's learner re-evaluates
its log-probs and values with its own network (and return scale) before the update; a batch acted
by the learner's own policy is used as stored, exactly as before (docs/research/learning.md)."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

import covers_dist.ppo.learner as ppo_learner
from covers_dist.config import load_config
from covers_dist.models.actor_critic import gaussian_log_prob
from covers_dist.ppo import PPOLearner, compute_gae
from covers_dist.runtime.driver import Trainer
from covers_dist.runtime.learner import PolicyLearner
from covers_dist.runtime.rollout import EpisodeSpec, RolloutWorker

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = [
    "runtime.serial=true",
    "runtime.num_workers=2",
    "runtime.envs_per_worker=4",
    "env.episodes_per_task=6",  # a task switch inside most batches of 4
    "env.max_episode_steps=10",
    "clustering.update_every=4",
    "clustering.feature_source=own",  # the tiny untrained nets split the toy tasks on their own features
    "ppo.epochs=1",
    "ppo.minibatch_size=40",
    "network.channels=[2,4]",
    "network.hidden=8",
    "runtime.log_every_s=1000",
    "runtime.checkpoint_every=100",
]


def tiny_cfg(tmp_path, *extra):
    return load_config("configs/smoke.yaml", [*TINY, f"runtime.run_dir={tmp_path}", *extra])


def act_batch(cfg, learner: PolicyLearner, version: int = 0) -> list[dict]:
    """Four episodes acted by ``learner``'s policy, as the runtime's rollout workers produce them."""
    runs = [("reach", "e", 0), ("reach", "r", 0), ("push", "f", 1), ("push", "e", 1)]
    specs = [EpisodeSpec(i, t, g, j) for i, (t, g, j) in enumerate(runs)]
    worker = RolloutWorker(cfg)
    try:
        return worker.sample(specs, learner.policy_id, version, learner.model.get_weights())
    finally:
        worker.close()


def capture_batches(monkeypatch) -> list[dict]:
    """Record the training tensors (old log-probs, old values, advantages, returns) of every update."""
    seen: list[dict] = []
    original = ppo_learner.episodes_to_batch

    def recording(*args, **kwargs):
        batch = original(*args, **kwargs)
        seen.append({k: v.clone() for k, v in batch.items()})
        return batch

    monkeypatch.setattr(ppo_learner, "episodes_to_batch", recording)
    return seen


def expected_from_network(model, episodes, ppo_cfg, return_norm) -> dict[str, np.ndarray]:
    """Old log-probs, values, advantages and returns computed directly from ``model`` and the
    return statistics ``return_norm`` (merged with this batch's rewards, as an update does)."""
    norm = copy.deepcopy(return_norm)
    norm.update([np.asarray(ep["reward"], np.float64) * ppo_cfg.reward_scale for ep in episodes])
    scale = ppo_cfg.reward_scale / norm.std
    out: dict[str, list] = {"logprob": [], "value": [], "adv": [], "ret": []}
    was_training = model.training
    model.eval()
    with torch.no_grad():
        for ep in episodes:
            obs = {"image": torch.from_numpy(ep["image"].copy()), "proprio": torch.from_numpy(ep["proprio"].copy())}
            mean, log_std, values = model(obs)
            t = len(ep["action"])
            logp = gaussian_log_prob(torch.from_numpy(ep["action"].copy()), mean[:t], log_std[:t])
            adv, ret = compute_gae(
                np.asarray(ep["reward"], np.float64) * scale, values.numpy(), ep["terminated"], ep["truncated"],
                ppo_cfg.gamma, ppo_cfg.gae_lambda,
            )  # fmt: skip
            out["logprob"].append(logp.numpy())
            out["value"].append(values.numpy()[:t])
            out["adv"].append(adv)
            out["ret"].append(ret)
    model.train(was_training)
    return {k: np.concatenate(v) for k, v in out.items()}


def test_a_batch_acted_by_another_policy_is_trained_with_the_assigned_policys_values_and_logprobs(
    tmp_path, monkeypatch
):
    cfg = tiny_cfg(tmp_path, "ppo.reward_norm=return", "ppo.precision=fp32")
    acting, assigned = PolicyLearner(cfg, 0), PolicyLearner(cfg, 1)
    # fresh networks act almost alike (means near 0, the same initial spread): move the acting
    # policy away from its initialisation, as training does
    gen = torch.Generator().manual_seed(7)
    moved = {k: w + 0.3 * torch.randn(w.shape, generator=gen) for k, w in acting.model.get_weights().items()}
    acting.model.set_weights(moved)
    # the two learners' return statistics differ (each has its own units), as after earlier updates
    acting.ppo.return_norm.load_state_dict({"count": 100, "mean": -2.0, "var": 9.0})
    assigned.ppo.return_norm.load_state_dict({"count": 50, "mean": -0.5, "var": 0.25})
    episodes = act_batch(cfg, acting, version=3)
    assert all(ep["policy_id"] == 0 for ep in episodes)
    stored = {k: np.concatenate([ep[k][: len(ep["action"])] for ep in episodes]) for k in ("logprob", "value")}
    ours = expected_from_network(assigned.model, episodes, cfg.ppo, assigned.ppo.return_norm)
    theirs = expected_from_network(acting.model, episodes, cfg.ppo, acting.ppo.return_norm)
    before = [{k: v.copy() for k, v in ep.items() if isinstance(v, np.ndarray)} for ep in episodes]

    seen = capture_batches(monkeypatch)
    stats, version, _ = assigned.update(episodes, base_version=0)
    batch = seen[0]
    n = sum(len(ep["action"]) for ep in episodes)
    assert version == 1 and stats["reevaluated_samples"] == n == stats["num_samples"]
    for key in ("logprob", "value", "adv", "ret"):
        np.testing.assert_allclose(batch[key].numpy(), ours[key], rtol=1e-4, atol=1e-4, err_msg=key)
        assert np.max(np.abs(batch[key].numpy() - theirs[key])) > 1e-2, key  # not the acting policy's
    for key in ("logprob", "value"):  # what the acting policy stored is what it computes itself
        np.testing.assert_allclose(stored[key], theirs[key], rtol=1e-4, atol=1e-4)
    # the assigned policy's first minibatch is on-policy: ratio 1 (one epoch, one minibatch here)
    assert stats["optimizer_steps"] == 1 and stats["approx_kl"] < 1e-6 and stats["clip_frac"] == 0.0
    # the episodes handed in are left as they were
    for ep, kept in zip(episodes, before):
        for k, v in kept.items():
            np.testing.assert_array_equal(ep[k], v)


def test_a_batch_acted_by_the_same_policy_at_an_older_version_is_used_as_stored(tmp_path, monkeypatch):
    """The normal path: episodes of the learner's own policy (here one version old, as when the loop
    is pipelined) are trained with their stored log-probs and values, bit for bit as a plain
    :meth:`PPOLearner.update` without re-evaluation does."""
    # one thread in both (the fixture's, the learner's): the same reductions, the same floats
    cfg = tiny_cfg(tmp_path, "ppo.epochs=2", "ppo.minibatch_size=20", "runtime.learner_threads=1")
    learner, twin = PolicyLearner(cfg, 1), PolicyLearner(cfg, 1)
    episodes = act_batch(cfg, learner, version=0)
    learner.update(act_batch(cfg, learner, version=0), base_version=0)  # now at version 1, the batch is one old
    twin.ppo.update(act_batch(cfg, twin, version=0))
    called = []
    monkeypatch.setattr(PPOLearner, "reevaluate", lambda self, eps: called.append(len(eps)))
    seen = capture_batches(monkeypatch)
    stats, version, weights = learner.update(episodes, base_version=1)
    plain = twin.ppo.update(episodes)  # the call as it was before batches could be re-evaluated
    assert version == 2 and stats["reevaluated_samples"] == 0 and not called
    np.testing.assert_array_equal(
        seen[0]["logprob"].numpy(), np.concatenate([ep["logprob"] for ep in episodes])
    )
    np.testing.assert_array_equal(
        seen[0]["value"].numpy(), np.concatenate([ep["value"][:-1] for ep in episodes])
    )
    for key in ("policy_loss", "value_loss", "approx_kl", "clip_frac", "grad_norm", "explained_variance"):
        assert stats[key] == plain[key], key
    theirs = twin.model.get_weights()
    assert weights.keys() == theirs.keys() and all(torch.equal(weights[k], theirs[k]) for k in weights)


def test_reevaluate_flags_are_checked_and_episodes_without_a_policy_id_are_used_as_stored(tmp_path):
    cfg = tiny_cfg(tmp_path)
    learner = PolicyLearner(cfg, 0)
    episodes = act_batch(cfg, learner)
    with pytest.raises(ValueError, match="one flag per episode"):
        learner.ppo.update(episodes, reevaluate=[True])
    bare = [{k: v for k, v in ep.items() if k not in ("policy_id", "policy_version")} for ep in episodes]
    assert learner.update(bare)[0]["reevaluated_samples"] == 0


def test_a_single_policy_run_never_reevaluates(tmp_path, monkeypatch):
    """With one policy (the `equi` baseline) no batch is acted by another policy: the update path is
    the one that was there before re-evaluation existed."""
    def refuse(self, episodes):
        raise AssertionError("a single-policy run re-evaluated a batch")

    monkeypatch.setattr(PPOLearner, "reevaluate", refuse)
    cfg = tiny_cfg(tmp_path, "runtime.method=equi", "runtime.total_env_steps=160")
    trainer = Trainer(cfg, log=lambda _m: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    counts = [r["ppo/reevaluated_samples"] for r in rows if "ppo/reevaluated_samples" in r]
    assert counts and all(c == 0 for c in counts)


def test_the_metrics_count_the_steps_of_episodes_acted_by_another_policy(tmp_path):
    """Sequential loop, Algorithm 1's order: each row's `ppo/reevaluated_samples` is the number of
    steps of that iteration's episodes whose acting policy is not the one they were assigned to."""
    cfg = tiny_cfg(tmp_path, "runtime.pipeline=false", "runtime.total_env_steps=480")
    trainer = Trainer(cfg, log=lambda _m: None)
    try:
        trainer.run()
    finally:
        trainer.close()
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    episodes = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    expected: dict[int, int] = {}
    for e in episodes:
        other = e["policy_id"] != e["assigned_policy"]
        expected[e["iteration"]] = expected.get(e["iteration"], 0) + (e["length"] if other else 0)
    got = {r["iteration"]: r["ppo/reevaluated_samples"] for r in rows}
    assert got == expected
    assert sum(got.values()) > 0  # the stream switches tasks inside batches: some were acted by another policy

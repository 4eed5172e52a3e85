"""GAE, the PPO loss, the learner (skips, early stop, schedule, checkpoints, determinism)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from covers_dist.cli import main as cli_main
from covers_dist.config import NetworkConfig, PPOConfig
from covers_dist.envs.toy import ToyTask, toy_layout
from covers_dist.models import build_actor_critic
from covers_dist.ppo import PPOLearner, ReturnNormalizer, collect_episodes, compute_gae, normalize_advantages, ppo_loss

SMALL_NET = NetworkConfig(channels=[2, 2, 2, 2], hidden=4)
LAYOUT = toy_layout(16)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ---- GAE -------------------------------------------------------------------------------------
def test_gae_single_final_reward_by_hand():
    rewards = np.array([0.0, 0.0, 0.0, 1.0])
    values = np.zeros(5)
    adv, ret = compute_gae(rewards, values, terminated=True, truncated=False, gamma=0.9, lam=1.0)
    np.testing.assert_allclose(ret, [0.9**3, 0.9**2, 0.9, 1.0], rtol=1e-6)
    np.testing.assert_allclose(adv, ret, rtol=1e-6)
    # with lambda = 0 only the one-step TD error remains: zero everywhere but the last step
    adv0, _ = compute_gae(rewards, values, True, False, gamma=0.9, lam=0.0)
    np.testing.assert_allclose(adv0, [0, 0, 0, 1.0], atol=1e-7)


def test_truncation_bootstraps_and_termination_does_not():
    rewards, values = np.array([1.0]), np.array([0.5, 2.0])
    adv_trunc, ret_trunc = compute_gae(rewards, values, terminated=False, truncated=True, gamma=0.9, lam=0.95)
    adv_term, ret_term = compute_gae(rewards, values, terminated=True, truncated=False, gamma=0.9, lam=0.95)
    assert adv_trunc[0] == pytest.approx(1.0 + 0.9 * 2.0 - 0.5)
    assert adv_term[0] == pytest.approx(1.0 - 0.5)
    assert ret_trunc[0] == pytest.approx(1.0 + 0.9 * 2.0)
    assert ret_term[0] == pytest.approx(1.0)


def reference_gae(rewards, values, terminated, gamma, lam):
    """A_t = sum_k (gamma * lam)^k delta_{t+k}, written as a plain double loop."""
    t_max = len(rewards)
    deltas = []
    for t in range(t_max):
        last = t == t_max - 1
        next_v = 0.0 if (last and terminated) else values[t + 1]
        deltas.append(rewards[t] + gamma * next_v - values[t])
    adv = []
    for t in range(t_max):
        adv.append(sum((gamma * lam) ** k * deltas[t + k] for k in range(t_max - t)))
    return np.array(adv), np.array(adv) + np.asarray(values[:-1])


@pytest.mark.parametrize("terminated", [True, False])
def test_gae_matches_a_plain_loop_reference(terminated):
    rng = np.random.default_rng(0)
    rewards, values = rng.normal(size=37), rng.normal(size=38)
    adv, ret = compute_gae(rewards, values, terminated, not terminated, gamma=0.97, lam=0.9)
    ref_adv, ref_ret = reference_gae(rewards, values, terminated, 0.97, 0.9)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret, ref_ret, rtol=1e-5, atol=1e-5)


def test_gae_rejects_wrong_lengths():
    with pytest.raises(ValueError, match="len\\(rewards\\) \\+ 1"):
        compute_gae(np.zeros(3), np.zeros(3), True, False, 0.9, 0.9)


# ---- loss ------------------------------------------------------------------------------------
def reference_loss(new_logp, old_logp, adv, v, v_old, ret, ent, eps, vclip, ent_coef, vf_coef):
    pg, vl = [], []
    for i in range(len(adv)):
        ratio = math.exp(new_logp[i] - old_logp[i])
        clipped_ratio = min(max(ratio, 1 - eps), 1 + eps)
        pg.append(-min(ratio * adv[i], clipped_ratio * adv[i]))
        v_clip = v_old[i] + min(max(v[i] - v_old[i], -vclip), vclip)
        vl.append(0.5 * max((v[i] - ret[i]) ** 2, (v_clip - ret[i]) ** 2))
    policy, value, entropy = np.mean(pg), np.mean(vl), np.mean(ent)
    return policy - ent_coef * entropy + vf_coef * value, policy, value


def test_ppo_loss_matches_an_independent_implementation():
    rng = np.random.default_rng(1)
    n = 64
    arrays = [rng.normal(size=n) * s for s in (0.3, 0.3, 1.0, 1.0, 1.0, 1.0, 1.0)]
    new_logp, old_logp, adv, v, v_old, ret, ent = arrays
    t = [torch.tensor(a) for a in arrays]
    terms = ppo_loss(*t, clip_coef=0.2, vf_clip_coef=0.3, ent_coef=0.01, vf_coef=0.5)
    loss, policy, value = reference_loss(new_logp, old_logp, adv, v, v_old, ret, ent, 0.2, 0.3, 0.01, 0.5)
    assert float(terms.loss) == pytest.approx(loss, rel=1e-9)
    assert terms.policy_loss == pytest.approx(policy, rel=1e-9)
    assert terms.value_loss == pytest.approx(value, rel=1e-9)
    ratio = np.exp(new_logp - old_logp)
    assert terms.clip_frac == pytest.approx(np.mean(np.abs(ratio - 1) > 0.2))
    assert terms.approx_kl == pytest.approx(np.mean((ratio - 1) - np.log(ratio)), rel=1e-9)
    unclipped = ppo_loss(*t, clip_coef=0.2, vf_clip_coef=None, ent_coef=0.0, vf_coef=1.0)
    assert unclipped.value_loss == pytest.approx(0.5 * np.mean((v - ret) ** 2), rel=1e-9)


def test_unmoved_policy_has_ratio_one_and_no_clipping():
    adv = torch.tensor([1.0, -2.0, 0.5, 3.0])
    logp = torch.tensor([-1.0, -0.3, -2.0, -0.7], requires_grad=True)
    zeros = torch.zeros(4)
    terms = ppo_loss(logp, logp.detach(), adv, zeros, zeros, zeros, zeros, 0.2, 0.2, 0.0, 0.0)
    assert terms.policy_loss == pytest.approx(-float(adv.mean()))  # clipped term == unclipped term
    assert terms.approx_kl == 0.0 and terms.clip_frac == 0.0
    terms.loss.backward()
    np.testing.assert_allclose(logp.grad.numpy(), -adv.numpy() / 4, rtol=1e-6)  # gradient of the unclipped term
    norm = normalize_advantages(adv)
    assert float(norm.mean()) == pytest.approx(0.0, abs=1e-6) and float(norm.std(unbiased=False)) == pytest.approx(1.0)


# ---- learner ---------------------------------------------------------------------------------
def make_model(seed: int = 0, kind: str = "equivariant"):
    return build_actor_critic(SMALL_NET, LAYOUT, kind=kind, seed=seed)


def make_episodes(model, n: int = 4, seed: int = 0):
    envs = [ToyTask("reach", "e", image_size=16, max_episode_steps=12) for _ in range(2)]
    return collect_episodes(model, envs, n, seed=seed, generator=torch.Generator().manual_seed(seed))


def weights_equal(a, b) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_first_minibatch_sees_ratio_one():
    model = make_model()
    cfg = PPOConfig(epochs=1, minibatch_size=48, vf_clip_coef=None)
    stats = PPOLearner(model, cfg).update(make_episodes(model))
    assert stats["optimizer_steps"] == 1 and stats["num_samples"] == 48
    assert stats["approx_kl"] < 1e-8 and stats["clip_frac"] == 0.0
    assert abs(stats["policy_loss"]) < 1e-5  # -mean of normalized advantages at ratio 1


def test_update_reports_stats_and_changes_weights():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(epochs=2, minibatch_size=16, lr=1e-3))
    before = model.get_weights()
    stats = learner.update(make_episodes(model))
    assert not weights_equal(before, model.get_weights())
    assert stats["optimizer_steps"] == 6 and stats["skipped_steps"] == 0 and stats["epochs_completed"] == 2
    for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_frac", "explained_variance", "grad_norm"):
        assert math.isfinite(stats[key]), key
    assert stats["lr"] == 1e-3 and stats["num_samples"] == 48 and learner.update_count == 1
    assert model.training


def test_nan_loss_or_gradient_skips_the_step_and_keeps_weights():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(epochs=2, minibatch_size=24))
    episodes = make_episodes(model)
    before = model.get_weights()
    bad = [dict(ep) for ep in episodes]
    bad[0]["reward"] = bad[0]["reward"].copy()
    bad[0]["reward"][-1] = np.nan  # GAE spreads it over the whole episode
    stats = learner.update(bad)
    assert stats["skipped_steps"] == 4 and stats["optimizer_steps"] == 0
    assert weights_equal(before, model.get_weights())
    handle = model.log_std_free.register_hook(lambda g: g * float("inf"))
    try:
        stats = learner.update(episodes)
    finally:
        handle.remove()
    assert stats["skipped_steps"] == 4 and weights_equal(before, model.get_weights())
    assert learner.skipped_total == 8
    assert learner.update(episodes)["skipped_steps"] == 0  # and it recovers


def test_bound_loss_is_zero_in_the_box_quadratic_beyond_and_invariant():
    from covers_dist.ppo.loss import SOFT_BOUND, bound_loss

    mean = torch.tensor([[0.3, -1.0, 1.1, -0.2], [1.6, -2.1, 0.0, 0.9]])
    expected = ((1.6 - SOFT_BOUND) ** 2 + (2.1 - SOFT_BOUND) ** 2) / 2  # mean over rows of the sum over entries
    assert float(bound_loss(mean)) == pytest.approx(expected)
    assert float(bound_loss(mean[:1])) == 0.0
    # a D4 element on (dx, dy) is a signed permutation: the penalty does not change
    moved = torch.stack([-mean[:, 1], mean[:, 0], mean[:, 2], mean[:, 3]], dim=1)
    assert float(bound_loss(moved)) == pytest.approx(expected)
    # ppo_loss adds it with its weight, and only with a mean given
    z = torch.zeros(4)
    base = ppo_loss(z, z, z, z, z, z, z, 0.2, None, 0.0, 0.5)
    with_bound = ppo_loss(z, z, z, z, z, z, z, 0.2, None, 0.0, 0.5, mean=torch.cat([mean, mean]), bound_coef=2.0)
    assert float(with_bound.loss - base.loss) == pytest.approx(2.0 * expected)
    assert with_bound.bound_loss == pytest.approx(expected) and base.bound_loss == 0.0


def test_a_linear_mean_outside_the_box_is_reported_and_pulled_back_by_the_bound():
    """The runaway this guards against: a linear mean far outside [-1, 1] (where the env's clipping
    makes the sampled noise carry no signal). ``mean_out_of_box`` reports it; ``bound_coef`` pulls
    the mean back towards the box."""
    net = dataclasses.replace(SMALL_NET, action_mean="linear")
    out = {}
    for coef in (0.0, 1.0):
        model = build_actor_critic(net, LAYOUT, seed=3)
        with torch.no_grad():  # a head grown large: most mean entries far outside the box
            for p in model.core.policy_head.parameters():
                p.mul_(1e5)
        episodes = make_episodes(model)
        learner = PPOLearner(model, PPOConfig(epochs=4, minibatch_size=24, lr=3e-3, bound_coef=coef))
        first = learner.update(episodes)  # measured on the data before this update's first step
        assert first["mean_out_of_box"] > 0.5
        for _ in range(5):
            stats = learner.update(episodes)
        out[coef] = stats
    assert out[1.0]["bound_loss"] > 0.0 and out[0.0]["bound_loss"] == 0.0
    assert out[1.0]["mean_out_of_box"] < out[0.0]["mean_out_of_box"]


def test_target_kl_stops_early():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(epochs=4, minibatch_size=8, lr=1e-2, target_kl=1e-6))
    stats = learner.update(make_episodes(model))
    assert stats["early_stopped"] and stats["optimizer_steps"] < 4 * 6


def test_kl_stop_from_the_update_start_ignores_how_stale_the_batch_is():
    """A batch acted one update ago (the pipelined loop's): measured from the behaviour policy the
    KL stop fires before the first step; measured from the update's start it reads this update's
    move only, so the update steps."""
    model = make_model()
    episodes = make_episodes(model)
    cfg = PPOConfig(minibatch_size=16, lr=1e-2, epochs=2, precision="fp32")
    learner = PPOLearner(model, cfg)
    learner.update(episodes)  # the policy moves on: the episodes are now one update old
    state = learner.state_dict()
    stale = PPOLearner(make_model(), dataclasses.replace(cfg, target_kl=1e-4))
    stale.load_state_dict(state)
    stats = stale.update(episodes)
    assert stats["early_stopped"] and stats["optimizer_steps"] == 0
    fresh = PPOLearner(make_model(), dataclasses.replace(cfg, target_kl=1e-4, kl_reference="update_start"))
    fresh.load_state_dict(state)
    stats = fresh.update(episodes)
    assert stats["optimizer_steps"] >= 1


def test_linear_learning_rate_schedule():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(lr=1e-3, lr_schedule="linear", total_updates=4, minibatch_size=48))
    episodes = make_episodes(model)
    lrs = [learner.update(episodes)["lr"] for _ in range(5)]
    np.testing.assert_allclose(lrs, [1e-3, 7.5e-4, 5e-4, 2.5e-4, 0.0])


def test_linear_entropy_schedule_falls_to_no_bonus():
    model = make_model()
    cfg = PPOConfig(minibatch_size=48, ent_coef=0.1, ent_schedule="linear", total_updates=2)
    learner = PPOLearner(model, cfg)
    episodes = make_episodes(model)
    coefs = []
    for _ in range(3):
        coefs.append(learner.entropy_coef())
        learner.update(episodes)
    np.testing.assert_allclose(coefs, [0.1, 0.05, 0.0])
    # past the horizon the update is the one without a bonus: same state, same episodes, same weights
    plain = PPOLearner(make_model(seed=3), dataclasses.replace(cfg, ent_coef=0.0, ent_schedule="constant"))
    plain.load_state_dict(learner.state_dict())
    learner.update(episodes)
    plain.update(episodes)
    for a, b in zip(learner.model.parameters(), plain.model.parameters()):
        assert torch.equal(a, b)
    # while the bonus is on, it changes the update
    fresh, other = make_model(), make_model()
    on = PPOLearner(fresh, cfg)
    off = PPOLearner(other, dataclasses.replace(cfg, ent_coef=0.0, ent_schedule="constant"))
    on.update(episodes)
    off.update(episodes)
    assert not all(torch.equal(a, b) for a, b in zip(fresh.parameters(), other.parameters()))
    with pytest.raises(ValueError, match="ppo.ent_schedule=linear needs ppo.total_updates"):
        PPOLearner(make_model(), PPOConfig(ent_coef=0.1, ent_schedule="linear", total_updates=None))


def test_a_null_horizon_is_the_runs_length_in_updates():
    from covers_dist.config import load_config

    # quickstart: 8 episodes of 100 steps per update; 200,000 env steps are 250 updates, 200,001 need 251
    for total, updates in ((200_000, 250), (200_001, 251), (10, 1)):
        cfg = load_config("quickstart", [f"runtime.total_env_steps={total}", "ppo.total_updates=null"])
        assert cfg.ppo.total_updates is None and cfg.learner_ppo.total_updates == updates
    cfg = load_config("quickstart", ["runtime.total_env_steps=200000", "ppo.total_updates=40"])
    assert cfg.learner_ppo is cfg.ppo and cfg.learner_ppo.total_updates == 40
    with pytest.raises(ValueError, match="Config.learner_ppo"):
        PPOLearner(make_model(), PPOConfig(lr_schedule="linear", total_updates=None))


def test_log_std_cap_falls_linearly_and_clips_the_learned_std():
    model = make_model()  # init_log_std -0.5 (NetworkConfig's default)
    start = float(model.log_std_free.detach().max())
    learner = PPOLearner(model, PPOConfig(lr=1e-3, minibatch_size=48, log_std_cap=-2.0, total_updates=4))
    episodes = make_episodes(model)
    caps = []
    for _ in range(6):
        stats = learner.update(episodes)
        caps.append(stats["log_std_cap"])
        assert float(model.log_std_free.detach().max()) <= stats["log_std_cap"] + 1e-7
    expected = [start + (-2.0 - start) * min(1.0, k / 4) for k in range(1, 7)]
    np.testing.assert_allclose(caps, expected, rtol=1e-6)
    assert caps[-1] == caps[-2] == -2.0  # held past the horizon
    # tied within planar pairs before and after: the clip keeps the policy equivariant
    assert torch.equal(model.log_std()[0], model.log_std()[1])
    # off: the statistic is None (no metrics column) and the std is left to the optimizer
    free = make_model()
    assert PPOLearner(free, PPOConfig(minibatch_size=48)).update(make_episodes(free))["log_std_cap"] is None


def test_log_std_cap_needs_a_horizon_and_survives_a_checkpoint():
    with pytest.raises(ValueError, match="ppo.log_std_cap needs ppo.total_updates"):
        PPOLearner(make_model(), PPOConfig(log_std_cap=-1.0, total_updates=None))
    cfg = PPOConfig(minibatch_size=48, log_std_cap=-1.5, total_updates=10)
    model = build_actor_critic(dataclasses.replace(SMALL_NET, init_log_std=0.0), LAYOUT, seed=0)
    learner = PPOLearner(model, cfg)
    episodes = make_episodes(model)
    learner.update(episodes)
    # a learner restored into a model built with another initial std starts its cap where the saved one did
    clone = PPOLearner(make_model(seed=4), cfg)
    clone.load_state_dict(learner.state_dict())
    assert clone.log_std_start == learner.log_std_start == 0.0
    assert clone.update(episodes)["log_std_cap"] == learner.update(episodes)["log_std_cap"] == pytest.approx(-0.3)


def test_weight_average_follows_the_updates_changes_no_training_and_stays_equivariant():
    """``ppo.weight_average``: avg = d * avg + (1 - d) * weights after every update, from the initial
    weights; the trained weights are those of a learner without it; it survives a checkpoint and
    is an exactly equivariant network."""
    from covers_dist.models import equivariance_errors

    runs = {}
    for decay in (None, 0.5):
        model = make_model(seed=3)
        learner = PPOLearner(model, PPOConfig(epochs=1, minibatch_size=48, lr=1e-3, weight_average=decay), seed=1)
        episodes = make_episodes(model, seed=2)
        seen = [model.get_weights()]
        for _ in range(2):
            learner.update(episodes)
            seen.append(model.get_weights())
        runs[decay] = (learner, seen)
    plain, averaged = runs[None], runs[0.5]
    assert all(weights_equal(a, b) for a, b in zip(plain[1], averaged[1]))  # training never reads the average
    w0, w1, w2 = averaged[1]
    avg = averaged[0].averaged_weights()
    for name in w0:
        torch.testing.assert_close(avg[name], 0.25 * w0[name] + 0.25 * w1[name] + 0.5 * w2[name], rtol=0, atol=1e-6)
    assert not weights_equal(avg, w2)
    with pytest.raises(ValueError, match="ppo.weight_average"):
        plain[0].averaged_weights()
    # a checkpoint keeps it; a state saved without one starts it from the saved weights
    clone = PPOLearner(make_model(seed=9), averaged[0].cfg)
    clone.load_state_dict(averaged[0].state_dict())
    assert weights_equal(clone.averaged_weights(), avg)
    clone.load_state_dict(plain[0].state_dict())
    assert weights_equal(clone.averaged_weights(), plain[1][-1])
    # the average is a network of the same group: exactly equivariant
    net = make_model(seed=5)
    net.set_weights(avg)
    episode = make_episodes(net, n=1)[0]
    obs = {"image": episode["image"][:3], "proprio": episode["proprio"][:3]}
    for g, row in equivariance_errors(net, obs).items():
        assert max(row.values()) < 1e-4, (g, row)


def test_peers_follow_the_learners_schedule_update_by_update():
    """bench learn's peers get covers-dist's linear schedule: SB3 through its learning-rate callable,
    RLlib through its piecewise schedule of env steps; each gives update k the learner's rate."""
    from ray.rllib.utils.schedules.piecewise_schedule import PiecewiseSchedule

    from covers_dist.bench.rllib_peer import lr_setting
    from covers_dist.bench.sb3_peer import UpdateSchedule

    batch, horizon, lr = 800, 5, 3e-4
    learner = PPOLearner(make_model(), PPOConfig(lr=lr, lr_schedule="linear", total_updates=horizon))
    hp = {"lr": lr, "lr_schedule": "linear", "lr_horizon_updates": horizon, "train_batch_env_steps": batch}
    points = lr_setting(hp)
    rllib = PiecewiseSchedule(points, outside_value=points[-1][-1], framework=None)
    sb3 = UpdateSchedule(lr, "linear", horizon, batch)
    sb3.model = type("Model", (), {"num_timesteps": 0})()
    for k in range(horizon + 3):
        learner.update_count = k
        sb3.model.num_timesteps = (k + 1) * batch  # SB3 updates after sampling its (k + 1)-th batch
        expected = learner.learning_rate()
        assert sb3(0.0) == pytest.approx(expected, abs=1e-12)
        assert rllib.value(k * batch) == pytest.approx(expected, abs=1e-12)  # set after update k - 1
    assert lr_setting({**hp, "lr_schedule": "constant"}) == lr


def test_same_seed_same_actions_and_losses():
    runs = []
    for _ in range(2):
        model = make_model(seed=3)
        learner = PPOLearner(model, PPOConfig(epochs=2, minibatch_size=16), seed=11)
        episodes = make_episodes(model, seed=5)
        stats = [learner.update(episodes) for _ in range(2)]
        runs.append((episodes, stats, model.get_weights()))
    (ep_a, st_a, w_a), (ep_b, st_b, w_b) = runs
    for a, b in zip(ep_a, ep_b):
        np.testing.assert_array_equal(a["action"], b["action"])
        np.testing.assert_array_equal(a["reward"], b["reward"])
    for a, b in zip(st_a, st_b):
        for key in ("policy_loss", "value_loss", "approx_kl", "grad_norm"):
            assert a[key] == b[key], key
    assert weights_equal(w_a, w_b)


@pytest.mark.parametrize("kind", ["equivariant", "cnn"])
def test_checkpoint_restores_model_optimizer_and_counters(kind):
    model = make_model(seed=0, kind=kind)
    cfg = PPOConfig(epochs=2, minibatch_size=16, lr_schedule="linear", total_updates=10)
    learner = PPOLearner(model, cfg, seed=2)
    episodes = make_episodes(model)
    learner.update(episodes)
    state = learner.state_dict()
    clone = PPOLearner(make_model(seed=9, kind=kind), cfg, seed=0)
    clone.load_state_dict(state)
    assert clone.update_count == 1
    a, b = learner.update(episodes), clone.update(episodes)
    assert a["policy_loss"] == b["policy_loss"] and a["lr"] == b["lr"]
    assert weights_equal(learner.model.get_weights(), clone.model.get_weights())
    with pytest.raises(ValueError, match="lacks keys"):
        clone.load_state_dict({"model": state["model"]})


def test_return_normalizer_merges_to_the_statistics_of_all_discounted_returns():
    rng = np.random.default_rng(0)
    episodes = [rng.uniform(0, 10, size=n) for n in (5, 9, 3, 12, 7)]
    norm = ReturnNormalizer(gamma=0.9)
    norm.update(episodes[:2])
    norm.update(episodes[2:])
    returns = []
    for r in episodes:  # G_t = r_t + gamma G_{t-1}, written out
        returns += [sum(0.9 ** (t - k) * r[k] for k in range(t + 1)) for t in range(len(r))]
    assert norm.count == len(returns)
    assert norm.mean == pytest.approx(np.mean(returns)) and norm.var == pytest.approx(np.var(returns))
    clone = ReturnNormalizer(gamma=0.9)
    clone.load_state_dict(norm.state_dict())
    assert clone.std == norm.std


def test_return_normalisation_makes_the_update_independent_of_the_reward_scale():
    """With reward_norm: return, rewards x1000 give the same update (Meta-World pays 0..10 a step,
    the toy tasks about -0.5): the value targets no longer depend on the task's reward units."""
    updated = []
    for factor in (1.0, 1000.0):
        model = make_model()
        episodes = make_episodes(model)
        for ep in episodes:
            ep["reward"] = np.asarray(ep["reward"]) * factor
        learner = PPOLearner(model, PPOConfig(epochs=2, minibatch_size=16, reward_norm="return"))
        stats = learner.update(episodes)
        assert stats["reward_divisor"] == pytest.approx(learner.return_norm.std / 0.1)  # after reward_scale 0.1
        updated.append(model.get_weights())
    for key in updated[0]:
        torch.testing.assert_close(updated[0][key], updated[1][key], rtol=1e-4, atol=1e-5)
    plain = PPOLearner(make_model(), PPOConfig(reward_norm="none"))
    assert plain.return_norm is None and plain.update(make_episodes(plain.model))["reward_divisor"] == pytest.approx(10.0)


def test_return_statistics_live_in_the_learner_state():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(epochs=1, minibatch_size=48))
    learner.update(make_episodes(model))
    state = learner.state_dict()
    assert state["return_norm"]["count"] == 48
    clone = PPOLearner(make_model(seed=3), PPOConfig(epochs=1, minibatch_size=48))
    clone.load_state_dict(state)
    assert clone.return_norm.state_dict() == learner.return_norm.state_dict()
    before = learner.return_norm.state_dict()
    short = dict(make_episodes(model)[0])
    short["value"] = short["value"][:-1]
    with pytest.raises(ValueError, match="episode 0: value"):
        learner.update([short])
    assert learner.return_norm.state_dict() == before  # a rejected batch leaves the statistics as they were
    older = {k: v for k, v in state.items() if k != "return_norm"}  # saved before return normalisation
    clone.load_state_dict(older)
    assert clone.return_norm.count == 0


def test_bad_episodes_fail_with_clear_errors():
    model = make_model()
    learner = PPOLearner(model, PPOConfig(minibatch_size=16))
    episodes = make_episodes(model, n=2)
    with pytest.raises(ValueError, match="at least one episode"):
        learner.update([])
    with pytest.raises(ValueError, match="lacks keys"):
        learner.update([{k: v for k, v in episodes[0].items() if k != "logprob"}])
    short = dict(episodes[0], value=episodes[0]["value"][:-1])
    with pytest.raises(ValueError, match="episode 0: value"):
        learner.update([short])
    with pytest.raises(TypeError, match="PPOConfig"):
        PPOLearner(model, dataclasses.asdict(PPOConfig()))


def test_bench_learner_prints_json(capsys):
    code = cli_main(
        ["bench", "learner", "--json", "--repeats", "1", "--samples", "64", "--channels", "2,2,2,2",
         "--hidden", "4", "--suites", "toy", "--inference-seconds", "0.05", "--env-steps", "20"]
    )  # fmt: skip
    assert code == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    kinds = {row["net"] for row in rows if row["kind"] == "net"}
    assert kinds == {"equivariant", "cnn", "cnn_matched_channels"}
    summary = [row for row in rows if row["kind"] == "summary"]
    assert summary and summary[0]["update_ratio_equivariant_to_cnn"] > 0
    assert {row["space_to_depth"] for row in rows if row["kind"] == "net"} == {1, 2}
    stems = [row for row in rows if row["kind"] == "stem"]
    assert {row["net"] for row in stems} == {"equivariant", "cnn"} and all(row["update_speedup"] > 0 for row in stems)
    assert {row["device"] for row in rows if row["kind"] in ("net", "summary")} == {"cpu"}
    with pytest.raises(SystemExit, match="--space-to-depth takes values among 1, 2, 4"):
        cli_main(["bench", "learner", "--space-to-depth", "3"])
    with pytest.raises(SystemExit, match="--device 'no-such-device' is not usable here"):
        cli_main(["bench", "learner", "--device", "no-such-device"])
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit, match="--device 'cuda' is not usable here"):
            cli_main(["bench", "learner", "--device", "cuda"])


def test_precision_resolves_to_native_bf16_only_and_a_bf16_update_keeps_fp32_weights(tmp_path):
    from covers_dist.config import NetworkConfig, PPOConfig
    from covers_dist.envs.toy import toy_layout
    from covers_dist.models import build_actor_critic
    from covers_dist.ppo import PPOLearner
    from covers_dist.ppo.learner import native_bf16_cpu, resolve_precision

    flags = tmp_path / "cpuinfo"
    flags.write_text("processor: 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16\n")
    assert native_bf16_cpu(str(flags))
    flags.write_text("processor: 0\nflags\t\t: fpu sse avx2\n")
    assert not native_bf16_cpu(str(flags))
    assert not native_bf16_cpu(str(tmp_path / "missing"))
    assert resolve_precision("fp32", "cpu") == "fp32" and resolve_precision("bf16", "cpu") == "bf16"
    assert resolve_precision("auto", "cpu") == ("bf16" if native_bf16_cpu() else "fp32")
    with pytest.raises(ValueError, match="precision must be"):
        resolve_precision("fp16", "cpu")

    model = build_actor_critic(NetworkConfig(channels=[2, 2], hidden=4), toy_layout(16), seed=0)
    learner = PPOLearner(model, PPOConfig(epochs=1, minibatch_size=32, precision="bf16"))
    rng = np.random.default_rng(0)
    t = 40
    obs = {"image": rng.integers(0, 256, (t + 1, 16, 16, 3), dtype=np.uint8),
           "proprio": rng.normal(size=(t + 1, model.layout.proprio_dim)).astype(np.float32)}
    actions, logp, values = model.act(obs)
    episode = {**obs, "action": actions[:t], "logprob": logp[:t], "value": values,
               "reward": rng.normal(size=t).astype(np.float32), "success": np.zeros(t, np.float32),
               "terminated": False, "truncated": True}  # fmt: skip
    before = model.get_weights()
    stats = learner.update([episode])
    assert stats["bf16"] and stats["optimizer_steps"] >= 1 and np.isfinite(stats["policy_loss"])
    after = model.get_weights()
    assert all(w.dtype == torch.float32 for w in after.values())
    assert any(not torch.equal(before[k], after[k]) for k in before)
    # at the first minibatch the policy is the behaviour policy: the fp32 log-prob path keeps the ratio ~1
    assert stats["approx_kl"] < 1e-2

"""The equivariant actor-critic, its CNN twin, fast inference and weight transport."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from covers_dist.config import NetworkConfig
from covers_dist.envs.layout import ObsLayout, transform_obs
from covers_dist.envs.toy import ToyTask, toy_layout
from covers_dist.models import ActorCritic, build_actor_critic, equivariance_errors
from covers_dist.models.checks import max_error
from covers_dist.symmetry import D4_ELEMENTS, get_group

METAWORLD_LAYOUT = ObsLayout(image_size=64, proprio_dim=4, proprio_pairs=1, action_dim=4, action_pairs=1)
LAYOUTS = {"toy32": toy_layout(32), "metaworld64": METAWORLD_LAYOUT}
TOL = 1e-4


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_obs(layout: ObsLayout, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    s = layout.image_size
    return {
        "image": rng.integers(0, 256, size=(n, s, s, 3), dtype=np.uint8),
        "proprio": rng.normal(size=(n, layout.proprio_dim)).astype(np.float32),
    }


def toy_obs(n: int, size: int = 32) -> dict[str, np.ndarray]:
    """Real toy observations (structured images, not noise)."""
    images, proprios = [], []
    for i in range(n):
        env = ToyTask(("reach", "push", "avoid")[i % 3], "e", image_size=size)
        obs, _ = env.reset(seed=i)
        for _ in range(3):
            obs, *_ = env.step(np.array([0.7, -0.4], np.float32))
        images.append(obs["image"])
        proprios.append(obs["proprio"])
    return {"image": np.stack(images), "proprio": np.stack(proprios)}


def to_torch(obs: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in obs.items()}


@pytest.fixture(scope="module")
def nets() -> dict[tuple[str, str], ActorCritic]:
    cfg = NetworkConfig()
    return {
        (name, kind): build_actor_critic(cfg, layout, kind=kind, seed=1)
        for name, layout in LAYOUTS.items()
        for kind in ("equivariant", "cnn")
    }


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
@pytest.mark.parametrize("mode", ["train", "eval"])
def test_equivariant_net_is_equivariant_for_every_element(nets, layout_name, mode):
    model = nets[(layout_name, "equivariant")]
    layout = LAYOUTS[layout_name]
    obs = random_obs(layout, 3, seed=2) if layout_name == "metaworld64" else toy_obs(3)
    model.train(mode == "train")
    try:
        errors = equivariance_errors(model, obs)
    finally:
        model.train()
    assert sorted(errors) == sorted(g.name for g in D4_ELEMENTS)
    for g, row in errors.items():
        assert set(row) == {"mean", "log_std", "value", "features"}
        assert max(row.values()) < TOL, (g, row)


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
def test_fast_inference_path_is_equivariant_and_matches_the_module(nets, layout_name):
    model = nets[(layout_name, "equivariant")]
    layout = LAYOUTS[layout_name]
    obs = random_obs(layout, 5, seed=3)
    assert max_error(equivariance_errors(model, obs, fast=True)) < TOL
    actions, _, values = model.act(obs, deterministic=True)
    with torch.no_grad():
        mean, _, value = model(to_torch(obs))
        feats = model.features(to_torch(obs)).numpy()
    np.testing.assert_allclose(actions, mean.numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(values, value.numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(model.features_np(obs), feats, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("layout_name", list(LAYOUTS))
def test_cnn_twin_is_not_invariant(nets, layout_name):
    model = nets[(layout_name, "cnn")]
    layout = LAYOUTS[layout_name]
    obs = toy_obs(3) if layout_name == "toy32" else random_obs(layout, 3, seed=4)
    errors = equivariance_errors(model, obs, group="D4")
    assert max(errors["e"].values()) == 0.0
    for g, row in errors.items():
        if g != "e":
            # features and value change when the scene is rotated or mirrored
            assert row["features"] > 0.01 and row["value"] > 1e-3, (g, row)
    assert max_error(errors) > 0.05


def test_twin_has_a_similar_parameter_count_and_same_interface(nets):
    for name in LAYOUTS:
        eq, cnn = nets[(name, "equivariant")], nets[(name, "cnn")]
        assert 0.67 < cnn.num_parameters() / eq.num_parameters() < 1.5
        obs = to_torch(random_obs(LAYOUTS[name], 2))
        for model in (eq, cnn):
            mean, log_std, value = model(obs)
            assert mean.shape == log_std.shape == (2, LAYOUTS[name].action_dim)
            assert value.shape == (2,)
            assert model.features(obs).shape == (2, model.feature_dim)
    assert nets[("toy32", "equivariant")].feature_dim == NetworkConfig().hidden


@pytest.mark.parametrize("group", ["C4", "D2", "C2", "D1", "trivial"])
def test_subgroups_build_and_are_equivariant(group):
    cfg = NetworkConfig(group=group, channels=[2, 2, 2, 2], hidden=4)
    model = build_actor_critic(cfg, toy_layout(32), seed=0)
    errors = equivariance_errors(model, random_obs(toy_layout(32), 2))
    assert sorted(errors) == sorted(g.name for g in get_group(group))
    assert max_error(errors, skip_identity=False) < TOL


def test_log_std_is_shared_within_planar_pairs():
    cfg = NetworkConfig(channels=[2, 2, 2, 2], hidden=4, init_log_std=-0.3)
    model = build_actor_critic(cfg, METAWORLD_LAYOUT, seed=0)
    with torch.no_grad():
        model.log_std_free.copy_(torch.tensor([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(model.log_std().detach().numpy(), [0.1, 0.1, 0.2, 0.3], rtol=1e-6)


def test_weights_round_trip_exactly_across_modes(nets):
    src = nets[("toy32", "equivariant")]
    dst = build_actor_critic(NetworkConfig(), toy_layout(32), seed=7)
    obs = random_obs(toy_layout(32), 4)
    src.eval()
    try:
        weights = src.get_weights()  # taken in eval mode
        dst.train()
        dst.set_weights(weights)  # loaded in train mode
        again = dst.get_weights()
        assert weights.keys() == again.keys()
        assert all(torch.equal(weights[k], again[k]) for k in weights)
        assert all(v.device.type == "cpu" and not v.requires_grad for v in weights.values())
        np.testing.assert_array_equal(src.act(obs, deterministic=True)[0], dst.act(obs, deterministic=True)[0])
        # a model in eval mode (cached escnn filters) picks the new weights up too
        other = build_actor_critic(NetworkConfig(), toy_layout(32), seed=8).eval()
        other.set_weights(weights)
        with torch.no_grad():
            np.testing.assert_array_equal(other(to_torch(obs))[0].numpy(), src(to_torch(obs))[0].numpy())
    finally:
        src.train()


def test_set_weights_rejects_mismatches(nets):
    model = nets[("toy32", "cnn")]
    weights = model.get_weights()
    key = next(iter(weights))
    with pytest.raises(ValueError, match="missing"):
        model.set_weights({k: v for k, v in weights.items() if k != key})
    with pytest.raises(ValueError, match="shape"):
        model.set_weights(dict(weights, **{key: torch.zeros(3, 3, 3)}))


def test_act_samples_reproducibly_and_reports_consistent_log_probs(nets):
    model = nets[("metaworld64", "equivariant")]
    obs = random_obs(METAWORLD_LAYOUT, 6)
    a1, lp1, v1 = model.act(obs, generator=torch.Generator().manual_seed(3))
    a2, lp2, v2 = model.act(obs, generator=torch.Generator().manual_seed(3))
    assert a1.dtype == lp1.dtype == v1.dtype == np.float32
    assert a1.shape == (6, 4) and lp1.shape == v1.shape == (6,)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_array_equal(lp1, lp2)
    a3, _, _ = model.act(obs, generator=torch.Generator().manual_seed(4))
    assert not np.allclose(a1, a3)
    with torch.no_grad():
        logp, entropy, value = model.evaluate_actions(to_torch(obs), torch.from_numpy(a1))
    np.testing.assert_allclose(lp1, logp.numpy(), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(v1, value.numpy(), rtol=1e-4, atol=1e-5)
    assert entropy.shape == (6,)


def test_fast_path_follows_in_place_parameter_updates():
    model = build_actor_critic(NetworkConfig(channels=[2, 2, 2, 2], hidden=4), toy_layout(32), seed=0)
    obs = random_obs(toy_layout(32), 3)
    before = model.act(obs, deterministic=True)[2]
    opt = torch.optim.SGD(model.parameters(), lr=0.5)
    value = model(to_torch(obs))[2]
    (value - 10.0).pow(2).mean().backward()
    opt.step()
    after = model.act(obs, deterministic=True)[2]
    with torch.no_grad():
        expected = model(to_torch(obs))[2].numpy()
    assert not np.allclose(before, after)
    np.testing.assert_allclose(after, expected, rtol=1e-4, atol=1e-5)


def test_features_np_is_chunked_and_matches_one_batch(nets):
    model = nets[("toy32", "equivariant")]
    obs = toy_obs(7)
    whole = model.features_np(obs)
    chunked = model.features_np(obs, chunk=3)
    assert whole.shape == (7, model.feature_dim)
    np.testing.assert_allclose(chunked, whole, rtol=1e-5, atol=1e-6)
    moved = model.features_np(transform_obs(model.layout, D4_ELEMENTS[5], obs))
    np.testing.assert_allclose(moved, whole, rtol=1e-4, atol=1e-5)


def test_same_seed_same_weights_and_kind_override():
    cfg = NetworkConfig(channels=[2, 2, 2, 2], hidden=4)
    a = build_actor_critic(cfg, toy_layout(32), seed=5).get_weights()
    b = build_actor_critic(cfg, toy_layout(32), seed=5).get_weights()
    c = build_actor_critic(cfg, toy_layout(32), seed=6).get_weights()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)
    assert build_actor_critic(cfg, toy_layout(32), kind="cnn").kind == "cnn"
    assert build_actor_critic(dataclasses.replace(cfg, kind="cnn"), toy_layout(32)).kind == "cnn"


def test_bad_inputs_fail_with_clear_errors(nets):
    model = nets[("toy32", "cnn")]
    obs = to_torch(random_obs(toy_layout(32), 2))
    with pytest.raises(ValueError, match="kind"):
        build_actor_critic(NetworkConfig(), toy_layout(32), kind="mlp")
    with pytest.raises(ValueError, match="divisible"):
        build_actor_critic(NetworkConfig(channels=[2, 2, 2, 2]), toy_layout(24), kind="cnn")
    with pytest.raises(TypeError, match="uint8"):
        model(dict(obs, image=obs["image"].float()))
    with pytest.raises(ValueError, match="shape"):
        model(dict(obs, image=obs["image"][:, :16]))
    with pytest.raises(ValueError, match="proprio"):
        model(dict(obs, proprio=obs["proprio"][:, :3]))
    with pytest.raises(TypeError, match="image"):
        model({"proprio": obs["proprio"]})
    with pytest.raises(ValueError, match="actions"):
        model.evaluate_actions(obs, torch.zeros(2, 3))


@pytest.mark.parametrize("k", [2, 4])
@pytest.mark.parametrize("layout_name", list(LAYOUTS))
def test_space_to_depth_stem_is_exactly_equivariant_on_every_path(layout_name, k):
    layout = LAYOUTS[layout_name]
    cfg = NetworkConfig(channels=[4, 8, 8, 16], hidden=16, space_to_depth=k)
    model = build_actor_critic(cfg, layout, seed=3)
    obs = toy_obs(3) if layout_name == "toy32" else random_obs(layout, 3, seed=5)
    for mode in (True, False):
        model.train(mode)
        assert max_error(equivariance_errors(model, obs)) < TOL
    assert max_error(equivariance_errors(model, obs, fast=True)) < TOL
    actions, _, values = model.act(obs, deterministic=True)
    with torch.no_grad():
        mean, _, value = model(to_torch(obs))
    np.testing.assert_allclose(actions, mean.numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(values, value.numpy(), rtol=1e-4, atol=1e-6)
    twin = build_actor_critic(cfg, layout, kind="cnn", seed=3)
    assert twin(to_torch(obs))[0].shape == mean.shape  # the twin takes the same stem
    assert max_error(equivariance_errors(twin, obs, group="D4")) > 0.01


@pytest.mark.parametrize("group", ["D4", "C4", "D1"])
def test_space_to_depth_representation_is_how_escnn_moves_the_folded_image(group):
    from escnn.nn import FieldType, GeometricTensor

    from covers_dist.models.equivariant import space_to_depth_repr
    from covers_dist.symmetry import escnn_gspace

    gs = escnn_gspace(group)
    rho = space_to_depth_repr(gs, 2)
    assert rho.size == 4 and space_to_depth_repr(gs, 2) is rho  # built once per group
    image = torch.rand(1, 3, 8, 8, dtype=torch.float64)
    plain = FieldType(gs, 3 * [gs.trivial_repr])
    folded = FieldType(gs, 3 * [rho])
    for h in gs.fibergroup.elements:
        moved_then_folded = torch.nn.functional.pixel_unshuffle(plain.transform(image, h), 2)
        folded_then_moved = GeometricTensor(torch.nn.functional.pixel_unshuffle(image, 2), folded).transform(h).tensor
        torch.testing.assert_close(moved_then_folded, folded_then_moved, rtol=0, atol=1e-9)


_PROBE_SCRIPT = """
import json, sys
import numpy as np
np.random.seed(int(sys.argv[1]))  # escnn's own decomposition would start from this state
from covers_dist.config import NetworkConfig
from covers_dist.envs.layout import ObsLayout
from covers_dist.models import build_actor_critic
from covers_dist.models.equivariant import space_to_depth_repr
from covers_dist.symmetry import escnn_gspace
layout = ObsLayout(image_size=64, proprio_dim=4, proprio_pairs=1, action_dim=4, action_pairs=1)
model = build_actor_critic(NetworkConfig(channels=[4, 8, 8, 16], hidden=16, space_to_depth=2), layout, seed=0)
bases = {g: space_to_depth_repr(escnn_gspace(g), 2).change_of_basis.tolist() for g in ("D4", "C4", "D1")}
print(json.dumps({"probe": model.probe_outputs().tolist(), "bases": bases}))
"""


def test_space_to_depth_network_is_the_same_function_in_every_process():
    """A learner and its rollout workers are different processes: the same weights must give the
    same policy in each, whatever their hash seed and numpy random state. A child process with a
    hash seed and a numpy random state of its own, against this process."""
    import json
    import os
    import subprocess
    import sys

    from covers_dist.models.equivariant import space_to_depth_repr
    from covers_dist.symmetry import escnn_gspace

    ours = os.environ.get("PYTHONHASHSEED", "")
    hash_seed = str((int(ours) + 1) % 2**32) if ours.isdigit() else "0"  # unset: this one's is random
    env = {**os.environ, "PYTHONHASHSEED": hash_seed}
    proc = subprocess.run(
        [sys.executable, "-c", _PROBE_SCRIPT, "1"], env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    child = json.loads(proc.stdout.strip().splitlines()[-1])
    bases = {g: space_to_depth_repr(escnn_gspace(g), 2).change_of_basis.tolist() for g in ("D4", "C4", "D1")}
    assert child["bases"] == bases
    here = build_actor_critic(NetworkConfig(channels=[4, 8, 8, 16], hidden=16, space_to_depth=2), METAWORLD_LAYOUT, seed=5)
    np.testing.assert_allclose(here.probe_outputs(), child["probe"], rtol=0, atol=1e-5)  # a wrong basis: ~1e-1


@pytest.mark.parametrize("group", ["D4", "C4", "D2", "C2", "D1"])
def test_canonical_change_of_basis_decomposes_without_randomness(group):
    from escnn.group._numerical import find_irreps_multiplicities_finitegroup

    from covers_dist.models.equivariant import canonical_change_of_basis, space_to_depth_repr
    from covers_dist.symmetry import escnn_gspace

    gs = escnn_gspace(group)
    rho = space_to_depth_repr(gs, 2)
    matrices = {g: rho(g) for g in gs.fibergroup.elements}
    np.random.seed(1)
    irreps, q = canonical_change_of_basis(matrices, gs.fibergroup)
    np.random.seed(2)
    irreps2, q2 = canonical_change_of_basis(matrices, gs.fibergroup)
    assert irreps == irreps2 and np.array_equal(q, q2)
    np.testing.assert_allclose(q.T @ q, np.eye(4), atol=1e-12)
    expected = [tuple(i) for i, m in find_irreps_multiplicities_finitegroup(matrices, gs.fibergroup) for _ in range(m)]
    assert irreps == expected
    assert np.array_equal(rho.change_of_basis, q)


def test_probe_outputs_leave_the_model_as_it_was_and_the_check_names_the_odd_process():
    from covers_dist.models.checks import check_same_function

    a = build_actor_critic(NetworkConfig(channels=[4, 8, 8, 16], hidden=16, space_to_depth=2), METAWORLD_LAYOUT, seed=0)
    b = build_actor_critic(NetworkConfig(channels=[4, 8, 8, 16], hidden=16, space_to_depth=2), METAWORLD_LAYOUT, seed=1)
    a.eval()
    obs = to_torch(random_obs(METAWORLD_LAYOUT, 3))
    before, weights = a(obs)[0], a.get_weights()
    state = torch.get_rng_state()
    probe = a.probe_outputs()
    assert torch.equal(torch.get_rng_state(), state) and not a.training
    assert all(torch.equal(weights[k], v) for k, v in a.get_weights().items())
    torch.testing.assert_close(a(obs)[0], before, rtol=0, atol=0)
    np.testing.assert_allclose(b.probe_outputs(), probe, rtol=0, atol=1e-6)  # the probe ignores the weights
    check_same_function({"rollout worker 0": probe, "learner of policy 0": b.probe_outputs()})
    other = build_actor_critic(NetworkConfig(channels=[4, 8, 8, 16], hidden=8, space_to_depth=2), METAWORLD_LAYOUT, seed=0)
    with pytest.raises(RuntimeError, match="learner of policy 3 builds a different network from rollout worker 0"):
        check_same_function({"rollout worker 0": probe, "learner of policy 3": other.probe_outputs()})
    skewed = probe.copy()
    skewed[0] += 0.05 * np.abs(probe).max()
    with pytest.raises(RuntimeError, match="rollout worker 1 and rollout worker 0 compute different functions"):
        check_same_function({"rollout worker 0": probe, "rollout worker 1": skewed})


def test_space_to_depth_cuts_the_work_and_block_sizes_validate():
    from covers_dist.models.equivariant import block_sizes

    assert block_sizes(64, 6, 1) == ([64, 32, 16, 8, 4, 2], 1)
    assert block_sizes(64, 6, 2) == ([32, 16, 8, 4, 2, 1], 1)
    assert block_sizes(64, 4, 4) == ([16, 8, 4, 2], 1)
    assert block_sizes(48, 4, 1) == ([48, 24, 12, 6], 3)
    with pytest.raises(ValueError, match="would pool a 5 x 5 map"):
        block_sizes(40, 4, 1)
    with pytest.raises(ValueError, match="divisible by space_to_depth=4"):
        block_sizes(66, 2, 4)
    small = build_actor_critic(NetworkConfig(space_to_depth=2), METAWORLD_LAYOUT, seed=0)
    full = build_actor_critic(NetworkConfig(space_to_depth=1), METAWORLD_LAYOUT, seed=0)
    assert small.num_parameters() < full.num_parameters()
    from torch.utils.flop_counter import FlopCounterMode

    obs = to_torch(random_obs(METAWORLD_LAYOUT, 2))
    counts = []
    for model in (full, small):
        with FlopCounterMode(display=False) as counter:
            model(obs)
        counts.append(counter.get_total_flops())
    assert counts[1] < counts[0] / 2.5  # about k^2 fewer FLOPs per sample


def test_proprio_norm_feeds_shifted_scaled_proprio_and_stays_equivariant():
    from covers_dist.envs import suite_layout

    layout = suite_layout("metaworld", 64)
    assert layout.has_proprio_stats
    raw = build_actor_critic(NetworkConfig(), layout, seed=4)
    normed = build_actor_critic(dataclasses.replace(NetworkConfig(), proprio_norm=True), layout, seed=4)
    # the statistics are fixed buffers, not weights: both nets hold the same parameters
    assert set(raw.get_weights()) == set(normed.get_weights())
    normed.set_weights(raw.get_weights())
    obs = random_obs(layout, 4, seed=5)
    shift, scale = np.asarray(layout.proprio_shift, np.float32), np.asarray(layout.proprio_scale, np.float32)
    pre = {"image": obs["image"], "proprio": ((obs["proprio"] - shift) * scale).astype(np.float32)}
    with torch.no_grad():
        mean_n, _, value_n = normed(to_torch(obs))
        mean_r, _, value_r = raw(to_torch(pre))
    np.testing.assert_allclose(mean_n.numpy(), mean_r.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(value_n.numpy(), value_r.numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(normed.act(obs, deterministic=True)[0], raw.act(pre, deterministic=True)[0], atol=1e-5)
    assert not np.allclose(mean_n.numpy(), raw(to_torch(obs))[0].detach().numpy(), atol=1e-6)
    assert max_error(equivariance_errors(normed, obs)) < TOL
    assert max_error(equivariance_errors(normed, obs, fast=True)) < TOL


@pytest.mark.parametrize("kind", ["equivariant", "cnn"])
def test_tanh_action_mean_stays_in_the_box_and_keeps_equivariance(kind):
    """The Gaussian's mean is tanh of the head's output: inside [-1, 1] however large the output grows
    (a linear mean drifts far outside the box the env clips to), on the module and the fast path, and
    the equivariant net stays exactly equivariant (tanh is odd: it commutes with D4's signed
    permutations of (dx, dy))."""
    layout = METAWORLD_LAYOUT
    cfg = NetworkConfig(channels=[2, 2, 2, 2], hidden=4)
    assert cfg.action_mean == "tanh"
    tanh = build_actor_critic(cfg, layout, kind=kind, seed=6)
    linear = build_actor_critic(dataclasses.replace(cfg, action_mean="linear"), layout, kind=kind, seed=6)
    with torch.no_grad():  # a head grown large, as the runaway runs' heads did (means of 10-24)
        for net in (tanh, linear):
            for name, p in net.core.named_parameters():
                if "policy" in name:
                    p.mul_(3000.0)
    assert set(tanh.get_weights()) == set(linear.get_weights())
    obs = random_obs(layout, 6, seed=7)
    with torch.no_grad():
        mean_t, log_std_t, value_t = tanh(to_torch(obs))
        mean_l, log_std_l, value_l = linear(to_torch(obs))
    assert float(mean_l.abs().max()) > 2.0  # the raw output leaves the action box
    np.testing.assert_allclose(mean_t.numpy(), np.tanh(mean_l.numpy()), rtol=1e-5, atol=1e-6)
    assert float(mean_t.abs().max()) <= 1.0
    np.testing.assert_array_equal(value_t.numpy(), value_l.numpy())
    np.testing.assert_array_equal(log_std_t.numpy(), log_std_l.numpy())
    greedy, logp, _ = tanh.act(obs, deterministic=True)  # the rollout path bounds the mean the same way
    np.testing.assert_allclose(greedy, mean_t.numpy(), atol=1e-5)
    sampled = tanh.act(obs, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        logp_module = tanh.evaluate_actions(to_torch(obs), torch.from_numpy(sampled[0]))[0].numpy()
    np.testing.assert_allclose(sampled[1], logp_module, rtol=1e-4, atol=1e-4)
    if kind == "equivariant":
        assert max_error(equivariance_errors(tanh, obs)) < TOL
        assert max_error(equivariance_errors(tanh, obs, fast=True)) < TOL
    with pytest.raises(ValueError, match="action_mean must be one of"):
        ActorCritic(tanh.core, layout, -0.5, kind, action_mean="sigmoid")


def test_proprio_statistics_are_checked_against_the_symmetry():
    base = dict(image_size=32, proprio_dim=4, proprio_pairs=1, action_dim=2, action_pairs=1)
    ObsLayout(**base, proprio_shift=(0.0, 0.0, 1.0, -2.0), proprio_scale=(3.0, 3.0, 0.5, 7.0))  # fine
    with pytest.raises(ValueError, match="planar pair 0"):
        ObsLayout(**base, proprio_shift=(0.1, 0.0, 0.0, 0.0), proprio_scale=(1.0, 1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="planar pair 0"):
        ObsLayout(**base, proprio_shift=(0.0, 0.0, 0.0, 0.0), proprio_scale=(1.0, 2.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="4 entries each"):
        ObsLayout(**base, proprio_shift=(0.0, 0.0), proprio_scale=(1.0, 1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="finite and > 0"):
        ObsLayout(**base, proprio_shift=(0.0, 0.0, 0.0, 0.0), proprio_scale=(1.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="no[n]e"):
        build_actor_critic(dataclasses.replace(NetworkConfig(), proprio_norm=True), toy_layout(32))


@pytest.mark.parametrize("kind", ["equivariant", "cnn"])
def test_bf16_update_forward_keeps_log_probs_in_fp32(nets, kind):
    """The learner's bf16 autocast forward must not shift the PPO ratio: its log-probs are fp32 and
    match the fp32 rollout's to well below an update's policy change (approximate KL ~1e-3)."""
    model = nets[("metaworld64", kind)]
    obs = random_obs(METAWORLD_LAYOUT, 16, seed=5)
    actions, lp_rollout, _ = model.act(obs, generator=torch.Generator().manual_seed(0))
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        logp, _, _ = model.evaluate_actions(to_torch(obs), torch.from_numpy(actions))
    assert logp.dtype == torch.float32
    logratio = logp.numpy() - lp_rollout
    assert np.abs(logratio).max() < 1e-3, np.abs(logratio).max()


def test_in_memory_clebsch_gordan_cache_gives_escnn_values_as_copies():
    """The in-memory cache in front of escnn's on-disk one returns exactly the disk values, as
    copies: a caller writing into the array it got does not change what the next caller gets."""
    import numpy as np

    from covers_dist.models._escnn_compat import import_escnn_nn

    import_escnn_nn()
    import escnn.group._clebsh_gordan as cg
    from escnn.group import dihedral_group

    group = dihedral_group(4)
    irreps = [irr.id for irr in group.irreps()]
    remembered = cg._clebsh_gordan_tensor
    assert getattr(remembered, "_covers_in_memory", False)
    m, n = irreps[-1], irreps[-1]
    for j, _ in cg._find_tensor_decomposition(m, n, "DihedralGroup", **group._keys):
        first = remembered(m, n, j, "DihedralGroup", **group._keys)
        expected = remembered.__wrapped__(m, n, j, "DihedralGroup", **group._keys)
        np.testing.assert_array_equal(first, expected)
        first[...] = 7.0
        np.testing.assert_array_equal(remembered(m, n, j, "DihedralGroup", **group._keys), expected)


def test_escnn_and_pot_are_imported_without_scikit_learn_and_both_still_import():
    """In a fresh process: building a network, a W1 distance and a bank's ARI leave scikit-learn
    unimported (escnn and POT took their fallbacks), and the network alone leaves ``scipy.stats``
    not yet loaded (escnn's init module holds it lazily; POT loads it); afterwards both import and work as usual, escnn's own use of
    ``scipy.stats`` included."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "import numpy as np\n"
        "from covers_dist.config import NetworkConfig\n"
        "from covers_dist.envs.layout import ObsLayout\n"
        "from covers_dist.models import build_actor_critic\n"
        "from covers_dist.clustering.distances import wasserstein1\n"
        "from covers_dist.clustering.metrics import adjusted_rand_index\n"
        "layout = ObsLayout(image_size=16, proprio_dim=4, proprio_pairs=1, action_dim=2, action_pairs=1)\n"
        "build_actor_critic(NetworkConfig(channels=[2], hidden=8, group='D4'), layout, seed=0)\n"
        "print(type(sys.modules['scipy.stats']).__name__)\n"
        "w = wasserstein1(np.zeros((2, 3)), np.ones((3, 3)))\n"
        "print('sklearn' in sys.modules, adjusted_rand_index([0, 1], [1, 0]))\n"
        "import escnn.group._numerical as numerical, escnn.nn.init as init, ot.lowrank, sklearn.metrics\n"
        "q = init.stats.ortho_group.rvs(3, random_state=0)\n"
        "print(numerical.randomized_svd is None, ot.lowrank.sklearn_import, round(w, 6) == round(3 ** 0.5, 6),\n"
        "      sklearn.metrics.adjusted_rand_score([0, 1], [1, 0]), np.allclose(q @ q.T, np.eye(3)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["_LazyModule", "False", "1.0", "True", "False", "True", "1.0", "True"], out.stdout


@pytest.mark.parametrize("kind", ["equivariant", "cnn"])
def test_separate_critic_keeps_the_policy_and_its_losses_apart(kind):
    """network.critic=separate: the actor is the shared build's (same seed, same mean and features),
    the value comes from its own core, each loss reaches only its own weights, the fast path is the
    module, and the equivariant pair stays exactly equivariant."""
    net = NetworkConfig(channels=[2, 4], hidden=4)
    shared = build_actor_critic(net, METAWORLD_LAYOUT, kind=kind, seed=3)
    split = build_actor_critic(dataclasses.replace(net, critic="separate"), METAWORLD_LAYOUT, kind=kind, seed=3)
    assert split.num_parameters() == 2 * shared.num_parameters() - shared.log_std_free.numel()
    obs = random_obs(METAWORLD_LAYOUT, 8)
    tens = {k: torch.from_numpy(v) for k, v in obs.items()}
    for model in (shared, split):
        model.eval()
    with torch.no_grad():
        (m1, _, v1), (m2, _, v2) = shared(tens), split(tens)
    torch.testing.assert_close(m1, m2)
    torch.testing.assert_close(shared.features_np(obs), split.features_np(obs))
    assert not torch.allclose(v1, v2)  # the critic core has its own weights
    actions, _, values = split.act(obs, deterministic=True)
    np.testing.assert_allclose(actions, m2.numpy(), atol=1e-5)
    np.testing.assert_allclose(values, v2.numpy(), atol=1e-5)
    split.train()
    for out, touched, untouched in ((1, "critic", "actor"), (0, "actor", "critic")):  # 1: the value, 0: the mean
        split.zero_grad(set_to_none=True)
        split(tens)[2 * out].sum().backward()  # (mean, log_std, value)
        grads = {n: p.grad for n, p in split.named_parameters() if n.startswith(f"core.{untouched}.")}
        assert grads and all(g is None or not g.any() for g in grads.values()), untouched
        assert any(p.grad is not None and p.grad.any() for n, p in split.named_parameters() if n.startswith(f"core.{touched}."))
    if kind == "equivariant":
        split.eval()
        assert max_error(equivariance_errors(split, obs)) < TOL
        assert max_error(equivariance_errors(split, obs, fast=True)) < TOL

"""The learned feature source the shipped configs cluster on (``clustering.feature_source: joint``).

Exact invariance under all of D4 on rendered Meta-World frames, that the bank of a
``stream_fast`` clustering service reads exactly these features, the cache, and the ``mono``
palette on which colours cannot tell the groups apart.
"""

from __future__ import annotations

import numpy as np
import pytest

from covers_dist.clustering import color_histogram, normalize_pair, wasserstein1
from covers_dist.clustering.joint import JointFeatures
from covers_dist.config import load_config
from covers_dist.envs import suite_layout
from covers_dist.envs.layout import transform_obs
from covers_dist.envs.metaworld_suite import MetaWorldTask
from covers_dist.models import build_actor_critic
from covers_dist.symmetry import D4_ELEMENTS

TASKS = ["reach-v3", "drawer-close-v3"]


def _first_frames(task: str, seeds: range, palette: str = "task") -> dict[str, np.ndarray]:
    env = MetaWorldTask(task, image_size=64, palette=palette)
    try:
        frames = [env.reset(seed=s)[0] for s in seeds]
    finally:
        env.close()
    return {k: np.stack([f[k] for f in frames]) for k in ("image", "proprio")}


@pytest.fixture(scope="module")
def frames() -> dict[str, dict[str, np.ndarray]]:
    return {t: _first_frames(t, range(10 * i, 10 * i + 6)) for i, t in enumerate(TASKS)}


@pytest.fixture(scope="module")
def models():
    """Two differently initialised ``stream_fast`` networks."""
    cfg = load_config("stream_fast", ["seed=0"])
    layout = suite_layout(cfg.env.suite, cfg.env.image_size)
    return cfg, layout, {pid: build_actor_critic(cfg.network, layout, seed=10 + pid).eval() for pid in (0, 1)}


def test_stream_fast_clusters_on_the_learned_joint_features(capsys):
    from covers_dist.cli import main

    assert main(["config", "--config", "stream_fast"]) == 0
    assert "feature_source: joint" in capsys.readouterr().out
    for name in ("stream_fast", "stream_cpu", "group_fast", "quickstart", "default"):
        assert load_config(name).clustering.feature_source == "joint", name


def test_joint_features_are_exactly_invariant_under_all_of_d4(models, frames):
    cfg, layout, nets = models
    joint = JointFeatures(lambda: {pid: (1, m.features_np) for pid, m in nets.items()})
    for task, obs in frames.items():
        base = joint(0, obs)
        assert base.shape == (6, 2 * cfg.network.hidden)
        np.testing.assert_allclose(np.linalg.norm(base.reshape(6, 2, -1), axis=2), 1.0, rtol=1e-6)
        for g in D4_ELEMENTS:
            moved = transform_obs(layout, g, obs)
            if g.name != "e":
                assert not np.array_equal(moved["image"], obs["image"]), g.name  # the frame did move
            np.testing.assert_allclose(joint(1, moved), base, atol=2e-5, err_msg=f"{task} {g.name}")
    assert len({g.name for g in D4_ELEMENTS}) == 8


def test_the_bank_measures_its_distances_in_the_joint_space(models, frames):
    """A ``stream_fast`` clustering service's bank reads the joint features of the policies it
    holds, and its recorded distances are W1 between exactly those features."""
    from covers_dist.runtime.clustering_service import ClusteringService

    cfg, _, nets = models
    svc = ClusteringService(cfg)
    assert isinstance(svc.bank.feature_fn, JointFeatures)
    weights = {pid: (1, m.get_weights()) for pid, m in nets.items()}
    svc.assign(0, frames["drawer-close-v3"], list(range(6)), [1] * 6, {0: weights[0]})
    assert len(svc.bank) == 1
    svc.sync_weights(weights)  # policy 1's weights arrived, but it is not in the bank: no block of its own
    reach = frames["reach-v3"]
    record = svc.what_if(reach)
    own = nets[0].features_np(reach)
    unit = own / np.linalg.norm(own, axis=1, keepdims=True)
    fn = svc.bank.feature_fn
    np.testing.assert_allclose(fn(0, reach), unit, rtol=1e-6)
    buffer = svc.bank.entries[0].buffer.observations()
    assert record["distances"]["0"] == pytest.approx(wasserstein1(*normalize_pair(fn(0, reach), fn(0, buffer), "buffer")))
    before = fn.encoded_frames
    svc.what_if(reach)
    assert fn.encoded_frames == before  # the same frames and weights: served from the cache


def test_joint_cache_reencodes_only_what_changed():
    calls: list[tuple[str, int]] = []

    def encoder(name: str, scale: float):
        def fn(obs):
            calls.append((name, len(obs["image"])))
            return obs["image"].reshape(len(obs["image"]), -1)[:, :3].astype(float) * scale + 1.0

        return fn

    rng = np.random.default_rng(0)
    obs = {"image": rng.integers(0, 255, (5, 4, 4, 3), dtype=np.uint8), "proprio": rng.normal(size=(5, 2)).astype(np.float32)}
    encoders = {0: (1, encoder("a", 1.0)), 1: (1, encoder("b", 2.0))}
    joint = JointFeatures(lambda: encoders)
    first = joint(0, obs)
    assert first.shape == (5, 6) and calls == [("a", 5), ("b", 5)]
    np.testing.assert_array_equal(joint(1, obs), first)  # one space for every policy
    assert calls == [("a", 5), ("b", 5)] and joint.encoded_frames == 10
    encoders[1] = (2, encoder("b", 3.0))  # policy 1 trained: only its block is encoded again
    joint(0, obs)
    assert calls[-1] == ("b", 5) and len(calls) == 3
    part = {k: v[:2] for k, v in obs.items()}
    joint(0, part)
    assert len(calls) == 3  # frames seen before come from the cache
    del encoders[0]
    assert joint(1, obs).shape == (5, 3)
    encoders[0] = (1, lambda o: np.zeros((1, 3)))
    with pytest.raises(ValueError, match="encoder of policy 0 returned shape"):
        joint(0, obs)
    with pytest.raises(LookupError, match="at least one policy"):
        JointFeatures(lambda: {})(0, obs)
    with pytest.raises(TypeError, match="callable"):
        JointFeatures({})
    with pytest.raises(ValueError, match="cache_frames"):
        JointFeatures(lambda: encoders, cache_frames=-1)


def test_mono_palette_hides_the_groups_from_the_colour_histogram():
    """Under ``env.palette: mono`` (one object colour, flat light) the four groups' first frames
    have nearly one colour histogram: their W1 is a small fraction of what it is under the task
    palette, where each task's objects have their own colours. The objects are still drawn."""

    def histograms(palette: str) -> list[np.ndarray]:
        tasks = ["reach-v3", "button-press-topdown-v3", "drawer-close-v3", "plate-slide-v3"]
        return [color_histogram(_first_frames(t, range(50 * i, 50 * i + 8), palette)) for i, t in enumerate(tasks)]

    def nearest_other(hs: list[np.ndarray]) -> float:
        return min(wasserstein1(a, b) for i, a in enumerate(hs) for b in hs[i + 1 :])

    task, mono = nearest_other(histograms("task")), nearest_other(histograms("mono"))
    assert mono < 0.05 * task, (mono, task)
    frame = _first_frames("drawer-close-v3", range(1), "mono")["image"][0]
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) == 3  # table, objects, the gripper's disc
    with pytest.raises(ValueError, match="palette must be one of"):
        MetaWorldTask("reach-v3", palette="pink")


def test_mono_palette_looks_the_same_through_mujocos_gl_camera():
    """The flat light is the model's own: MuJoCo's GL renderer draws the mono frame as the numpy one."""
    frames = []
    for backend in ("numpy", "egl"):
        env = MetaWorldTask("drawer-close-v3", image_size=64, palette="mono", render_backend=backend)
        try:
            frames.append(env.reset(seed=3)[0]["image"].astype(int))
        finally:
            env.close()
    assert np.abs(frames[0] - frames[1]).mean() < 1.0


def test_mono_palette_is_a_metaworld_config_value():
    from covers_dist.config import ConfigError

    assert load_config("stream_fast", ["env.palette=mono"]).env.palette == "mono"
    with pytest.raises(ConfigError, match="palette"):
        load_config("smoke", ["env.palette=mono"])
    with pytest.raises(ConfigError, match="palette"):
        load_config("stream_fast", ["env.palette=grey"])

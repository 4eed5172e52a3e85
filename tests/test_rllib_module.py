"""covers-dist's actor-critic as an RLlib RLModule: RLlib's PPO trains the same network."""

import numpy as np
import pytest
import torch

from covers_dist.config import load_config
from covers_dist.envs.layout import transform_obs
from covers_dist.symmetry import get_group

TINY = [
    "env.tasks=[reach]",
    "network.channels=[2,2]",
    "network.hidden=4",
    "network.space_to_depth=2",
    "clustering.update_every=2",
    "env.max_episode_steps=20",
    "ppo.minibatch_size=20",
    "ppo.epochs=1",
    "runtime.num_workers=1",
    "runtime.envs_per_worker=1",
]


def _cfg(*extra):
    return load_config("configs/smoke.yaml", [*TINY, *extra])


@pytest.mark.parametrize("kind", ["equivariant", "cnn"])
def test_module_outputs_match_the_covers_network_and_stay_equivariant(kind):
    from ray.rllib.core.columns import Columns

    from covers_dist.integrations.rllib import covers_rl_module_spec
    from covers_dist.models import build_actor_critic

    extra = ["network.kind=cnn", "runtime.method=covers-cnn"] if kind == "cnn" else []
    cfg = _cfg(*extra)
    spec = covers_rl_module_spec(cfg)
    from covers_dist.integrations.rllib import CoversTaskEnv, covers_env_config

    env = CoversTaskEnv(covers_env_config(cfg))
    spec.observation_space, spec.action_space = env.observation_space, env.action_space
    module = spec.build()
    obs, _ = env.reset(seed=0)
    batch = {Columns.OBS: {k: torch.from_numpy(np.asarray(v)[None]) for k, v in obs.items()}}
    out = module.forward_train(batch)
    same = build_actor_critic(cfg.network, module.net.layout, seed=cfg.seed)
    mean, log_std, value = same({k: v for k, v in batch[Columns.OBS].items()})
    dist = out[Columns.ACTION_DIST_INPUTS]
    torch.testing.assert_close(dist, torch.cat([mean, log_std], -1))
    torch.testing.assert_close(module.compute_values(batch, out[Columns.EMBEDDINGS]), value)
    torch.testing.assert_close(module.compute_values(batch), value)
    fast = module.forward_inference(batch)[Columns.ACTION_DIST_INPUTS]
    torch.testing.assert_close(fast, dist.detach(), rtol=1e-4, atol=1e-6)
    if kind == "equivariant":
        layout = module.net.layout
        base = {k: np.asarray(v)[None] for k, v in obs.items()}
        for g in get_group("D4"):
            moved = transform_obs(layout, g, base)
            got = module.forward_inference({Columns.OBS: {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in moved.items()}})
            want = layout.transform_action(g, fast[:, : layout.action_dim].numpy())
            np.testing.assert_allclose(got[Columns.ACTION_DIST_INPUTS][:, : layout.action_dim].numpy(), want, atol=1e-5)
    env.close()


def test_rllib_ppo_trains_the_covers_network(ray_local):
    from covers_dist.bench.rllib_peer import build_rllib_ppo, rllib_hyperparameters
    from test_bench_learn import assert_equal_terms

    cfg = _cfg("ppo.lr_schedule=linear", "ppo.target_kl=0.02")
    algo = build_rllib_ppo(cfg, "covers")
    try:
        # on equal terms: covers-dist's PPO settings, read back from the built algorithm
        assert_equal_terms(rllib_hyperparameters(algo, "covers", cfg), cfg)
        module = algo.get_module()
        before = {k: v.detach().clone() for k, v in module.net.named_parameters()}
        result = algo.train()
        assert result["env_runners"]["num_env_steps_sampled"] >= 40
        after = dict(algo.get_module().net.named_parameters())
        assert any(not torch.equal(before[k], after[k].detach()) for k in before)
    finally:
        algo.stop()
    with pytest.raises(ValueError, match="network must be 'default' or 'covers'"):
        build_rllib_ppo(_cfg(), "resnet")

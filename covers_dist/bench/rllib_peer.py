"""RLlib's PPO on the same task as a covers-dist config: the peer ``bench train`` measures against.

RLlib's default catalog builds a CNN encoder for image observations, so the peer sees the same
top-down image (same renderer, same size) without the proprio vector, through a CNN whose
channel widths follow ``network.channels`` (stride-2 4x4 convolutions down to a small map).
Sampling uses ``runtime.num_workers`` env runners with ``runtime.envs_per_worker`` envs each, and
one train batch is one covers-dist iteration's worth of env steps.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from ..config import Config

__all__ = ["ImageOnlyTask", "build_rllib_ppo"]


class ImageOnlyTask(gym.Env):
    """A covers-dist task with only the image (as floats in [0, 1]) as observation."""

    metadata = {"render_modes": []}

    def __init__(self, env_config: dict[str, Any]) -> None:
        from ..config import config_from_dict
        from ..envs import make_task

        cfg = config_from_dict(env_config["config"])
        self.inner = make_task(cfg.env, env_config["task"], "e")
        size = cfg.env.image_size
        # RLlib's CNN encoder takes float input: the same image scaled to [0, 1]
        self.observation_space = gym.spaces.Box(0.0, 1.0, (size, size, 3), np.float32)
        self.action_space = self.inner.action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.inner.reset(seed=seed)
        return _scaled(obs["image"]), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.inner.step(action)
        return _scaled(obs["image"]), reward, terminated, truncated, info

    def close(self) -> None:
        self.inner.close()


def _scaled(image: np.ndarray) -> np.ndarray:
    return image.astype(np.float32) * (1.0 / 255.0)


def build_rllib_ppo(cfg: Config, network: str = "default") -> Any:
    """An RLlib PPO algorithm (new API stack) configured like ``cfg`` (Ray must be initialised).

    ``network="default"``: RLlib's own CNN on the image alone; ``"covers"``: covers-dist's network
    (``cfg.network``: the equivariant net or its CNN twin) as an RLModule on image + proprio
    (:mod:`covers_dist.integrations.rllib`), so the two frameworks are compared on equal compute.
    """
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
    from ray.tune.registry import register_env

    from ..config import config_to_dict

    if network not in ("default", "covers"):
        raise ValueError(f"network must be 'default' or 'covers', got {network!r}")
    register_env("covers_image_task", lambda env_config: ImageOnlyTask(env_config))
    batch = cfg.clustering.update_every * cfg.env.max_episode_steps
    per_runner = max(1, batch // (cfg.runtime.num_workers * cfg.runtime.envs_per_worker))
    filters = []
    size = cfg.env.image_size
    for i, ch in enumerate(cfg.network.channels):
        if size <= 4:
            break
        filters.append([int(ch) * 4, 4, 2])  # ~ the equivariant net's width (regular fields x |D4| / 2)
        size //= 2
    if network == "covers":
        from ..integrations.rllib import covers_env_config, covers_rl_module_spec, register_covers_env

        env_name, env_config = register_covers_env(), covers_env_config(cfg)
        module = {"rl_module_spec": covers_rl_module_spec(cfg)}
    else:
        env_name, env_config = "covers_image_task", {"config": config_to_dict(cfg), "task": cfg.env.tasks[0]}
        module = {"model_config": DefaultModelConfig(conv_filters=filters, head_fcnet_hiddens=[cfg.network.hidden])}
    algo_cfg = (
        PPOConfig()
        .environment(env_name, env_config=env_config)
        .framework("torch")
        .env_runners(
            num_env_runners=cfg.runtime.num_workers,
            num_envs_per_env_runner=cfg.runtime.envs_per_worker,
            rollout_fragment_length=per_runner,
            num_cpus_per_env_runner=1,
        )
        .learners(num_learners=0)
        .training(
            train_batch_size_per_learner=batch,
            minibatch_size=min(cfg.ppo.minibatch_size, batch),
            num_epochs=cfg.ppo.epochs,
            lr=cfg.ppo.lr,
            gamma=cfg.ppo.gamma,
            lambda_=cfg.ppo.gae_lambda,
            clip_param=cfg.ppo.clip_coef,
        )
        .rl_module(**module)
        .debugging(seed=cfg.seed)
        .reporting(min_sample_timesteps_per_iteration=0)
    )
    return algo_cfg.build_algo()
